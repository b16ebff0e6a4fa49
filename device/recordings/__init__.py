"""tactile.device.recordings: the take format and everything that reads or writes takes.

A take is ``NAME.csv`` (what the pen sent) plus ``NAME.json`` beside it (label, device header,
gaps); a dataset is a folder of takes (:mod:`~tactile.device.recordings.take`). Takes are
written by :class:`TakeWriter` (the :class:`Recorder` reading a pen, or the importers:
:func:`import_hapmat`, :mod:`~tactile.device.recordings.biotac` with the ``[biotac]`` extra) and
read back by :func:`read_take` and :func:`load_dataset`; :func:`summarise` and the plots
(:mod:`~tactile.device.recordings.plot`, the ``[train]`` extra) describe a dataset.
"""

from tactile.device.recordings.hapmat import import_hapmat
from tactile.device.recordings.plot import plot_summary, plot_take
from tactile.device.recordings.reader import iter_takes, load_dataset, load_numbers, read_take
from tactile.device.recordings.recorder import Recorder, RecordResult, record
from tactile.device.recordings.summary import HOP, WINDOW, summarise, windows_in
from tactile.device.recordings.take import (
    LABEL_RULE,
    Take,
    check_label,
    dataset_folder,
    replace_takes,
)
from tactile.device.recordings.take_meta import FORMAT, VERSION, read_meta
from tactile.device.recordings.writer import TakeWriter

__all__ = [
    "FORMAT", "HOP", "LABEL_RULE", "RecordResult", "Recorder", "Take", "TakeWriter", "VERSION",
    "WINDOW", "check_label", "dataset_folder", "import_hapmat", "iter_takes", "load_dataset",
    "load_numbers", "plot_summary", "plot_take", "read_meta", "read_take", "record",
    "replace_takes", "summarise", "windows_in",
]
