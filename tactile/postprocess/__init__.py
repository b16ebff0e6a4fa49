"""tactile.postprocess: the label stream's post-processing, numpy only, shared by the stages.

The runtime post-processes each pen's labels with it, the exporter calibrates a file's defaults
with it and ``tactile-eval`` measures a run's label stream with it; it imports only the standard
library, numpy and the core (:mod:`tactile.errors`, :mod:`tactile.contract`).

* :mod:`~tactile.postprocess.smoothing`: :class:`PostProcessor` (averaged probabilities, a
  stable label or :data:`UNCERTAIN`, change events), :class:`SmoothingSettings`, and the
  ``postprocess.*`` metadata keys.
* :mod:`~tactile.postprocess.metrics`: a :class:`WindowStream` against its truth (accuracy,
  share uncertain, false changes per minute, change latency), raw and smoothed.
* :mod:`~tactile.postprocess.calibration`: :func:`calibrate`, a setting chosen on validation
  streams.
* :mod:`~tactile.postprocess.streams`: sample streams made of pieces of takes, neighbours of
  different classes, and the truth of the windows a model makes on them.
"""

from tactile.postprocess.calibration import MAX_FALSE_PER_MIN, Calibration, calibrate
from tactile.postprocess.metrics import WindowStream, compare, figures
from tactile.postprocess.smoothing import (
    UNCERTAIN,
    PostProcessor,
    SmoothingSettings,
    check_classes,
    settings_from_metadata,
    settings_to_metadata,
)
from tactile.postprocess.streams import (
    Piece,
    SampleStream,
    join,
    make_streams,
    run_pieces,
    shortfall,
    window_stream,
)

__all__ = [
    "MAX_FALSE_PER_MIN", "UNCERTAIN", "Calibration", "Piece", "PostProcessor", "SampleStream",
    "SmoothingSettings", "WindowStream", "calibrate", "check_classes", "compare", "figures",
    "join", "make_streams", "run_pieces", "settings_from_metadata", "settings_to_metadata",
    "shortfall", "window_stream",
]
