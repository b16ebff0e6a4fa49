"""Import the BioTac BOLT recordings (two BioTac fingertips on a robot hand, 5 objects) as takes
(``tactile-import-biotac``). Needs h5py (the ``[biotac]`` extra).

The recordings come from the Penn-haptics-bolt repository (``training_tests/<object>.h5``, no
licence stated: development and evaluation only). Each HDF5 file holds one group per trial,
``<object>_pdc<setting>_<depth>_<repetition>`` (e.g. ``cork_pdc150_1cm_03``), with
``finger_0/`` and ``finger_1/`` each holding ``pac`` (T, 22), ``pdc`` (T,), ``electrodes``
(T, 19), ``tac`` (T,) and ``tdc`` (T,), plus ``timestamps`` (T,) in whole Unix seconds.

Each trial becomes one take named after its group, labelled with its object, at 100 Hz (one row
per 10 ms frame). The take's metadata says ``trial`` (the group name), ``pdc_setting`` (the
contact-pressure setting, e.g. 150), ``repetition`` (1..5) and ``user``: the repetition, so that
``split = "user"`` keeps every trial of one repetition (all objects, all pressures) in one
split. Channels, 44 per finger (:func:`channels`): ``f0_pac_00`` .. ``f0_pac_21`` (the 22
vibration sub-samples of a frame, in time order: one 2.2 kHz signal), ``f0_pdc``,
``f0_ele_00`` .. ``f0_ele_18``, ``f0_tac``, ``f0_tdc``, then the same for ``f1``. Values are the
raw 12-bit ADC counts as recorded: unit ``count``, scale 1. The JSON's ``signals`` declares
each finger's vibration channels one high-rate signal (:func:`signals`: ``f0_pac``, ``f1_pac``).

Every input is checked before anything is written: a file that is not HDF5, a trial group whose
name or datasets are not as above, an HDF5 link in place of a trial or dataset that leads
nowhere (an external link to a missing file, a soft link to a path the file lacks; links that
lead to the data are followed), a dataset that cannot be read (a damaged chunk), lengths that
disagree, values that are not 12-bit counts, timestamps that are not whole Unix seconds of
1970..2099 (:data:`FIRST_TIME` .. :data:`LAST_TIME`), or a trial given twice, is one line naming
the file and the dataset, exit code 1. Timestamps that go back, or jump by more than a second
between two frames (frames lost, or the recording computer's clock set), are imported all the
same, in file order (the order the frames were recorded in), with one ``warning:`` line per
trial naming the first such frame. A take of the same name already in the output folder is
refused too (importing twice would duplicate data), or replaced with ``--force``: each old take
only once every input has passed its checks (the takes' metadata included), so a bad input
leaves them as they were, and then only once its new take is whole.
"""

from __future__ import annotations

import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from tactile.cli import prefix as command_prefix
from tactile.device.protocol.info import ChannelSpec, DeviceInfo
from tactile.device.recordings.take import (
    check_label,
    dataset_folder,
    replace_takes,
    whole_take,
)
from tactile.device.recordings.writer import TakeWriter
from tactile.errors import RecordingError

RATE_HZ = 100.0
FINGERS = (0, 1)
PAC_SAMPLES = 22  # vibration sub-samples per 10 ms frame (2.2 kHz)
ELECTRODES = 19
ADC_MAX = 4095  # 12-bit counts
# the timestamps a trial may hold, whole Unix seconds: 1970-01-01 .. 2099-12-31 UTC (the
# recordings are of 2012; a value beyond is a damaged file, not a date)
FIRST_TIME, LAST_TIME = 0, 4_102_444_799
# (dataset in finger_<k>/, columns or None for a 1-D dataset, channel prefix); the order of the
# channels in a take
MODALITIES = (
    ("pac", PAC_SAMPLES, "pac"),
    ("pdc", None, "pdc"),
    ("electrodes", ELECTRODES, "ele"),
    ("tac", None, "tac"),
    ("tdc", None, "tdc"),
)
TRIAL = re.compile(r"^(?P<object>[a-z0-9_]+?)_pdc(?P<pdc>\d+)_(?P<depth>[a-z0-9]+)_(?P<rep>\d+)$")
ORIGIN = "Penn-haptics-bolt repository, commit 441c64d, training_tests/"
LICENCE = "none stated upstream: development and evaluation only, never redistributed"


def channels(fingers: tuple[int, ...] = FINGERS) -> tuple[ChannelSpec, ...]:
    """The take's channels, in column order: 44 per finger, raw counts (scale 1)."""
    out = []
    for k in fingers:
        for _, width, prefix in MODALITIES:
            names = [f"f{k}_{prefix}"] if width is None else [
                f"f{k}_{prefix}_{i:02d}" for i in range(width)]
            out += [ChannelSpec(n, "count") for n in names]
    return tuple(out)


@dataclass(frozen=True)
class Trial:
    """One trial group of one file."""

    file: Path
    group: str
    label: str
    pdc_setting: int
    depth: str
    repetition: int


def _open(path: Path) -> h5py.File:
    if path.is_dir():
        raise RecordingError(f"{path}: a folder; give the .h5 files (e.g. {path / '*.h5'})")
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise RecordingError(f"{path}: not an HDF5 file ({str(e).splitlines()[0]})") from None


def _node(group: h5py.Group, name: str, where: str) -> h5py.HLObject | None:
    """The object at ``name`` (a path inside ``group``, e.g. ``finger_0/pdc``), or None when
    there is none. A link on the way that leads nowhere (a soft link to a path the file does
    not hold, an external link to a file that is missing or lacks the path) is
    :class:`RecordingError` ``"<where><name>: ..."`` saying which link (h5py's KeyError
    names neither the file nor the dataset)."""
    node, parts = group, name.split("/")
    for i, part in enumerate(parts):
        link = node.get(part, getlink=True) if isinstance(node, h5py.Group) else None
        if link is None:
            return None
        try:
            node = node[part]
        except (KeyError, OSError, ValueError) as e:
            why = str(e.args[0] if e.args else "").splitlines()[0:1] or [type(e).__name__]
            to = (f"{link.path} in {link.filename}" if isinstance(link, h5py.ExternalLink)
                  else link.path if isinstance(link, h5py.SoftLink) else None)
            what = f"a link to {to} that cannot be followed" if to else "cannot be opened"
            here = "" if i == len(parts) - 1 else f"{'/'.join(parts[: i + 1])} is "
            raise RecordingError(f"{where}{name}: {here}{what} ({why[0]})") from None
    return node


def _trials(path: Path, f: h5py.File) -> list[Trial]:
    """The trial groups of an open file, named as the layout says."""
    out = []
    for name in sorted(f.keys()):
        if not isinstance(_node(f, name, f"{path}: "), h5py.Group):
            raise RecordingError(f"{path}: {name}: a dataset where a trial group was expected")
        m = TRIAL.match(name)
        if m is None:
            raise RecordingError(f"{path}: group {name!r} is not named "
                                 "<object>_pdc<setting>_<depth>_<repetition>")
        try:
            check_label(m["object"])
        except RecordingError as e:
            raise RecordingError(f"{path}: group {name!r}: {e}") from None
        out.append(Trial(path, name, m["object"], int(m["pdc"]), m["depth"], int(m["rep"])))
    if not out:
        raise RecordingError(f"{path}: no trial groups")
    return out


def read_trial(f: h5py.File, trial: Trial) -> tuple[np.ndarray, np.ndarray]:
    """The trial's raw counts (T, 88) int64 in :func:`channels` order and its timestamps (T,)
    in Unix seconds (:data:`FIRST_TIME` .. :data:`LAST_TIME`). Raises :class:`RecordingError`
    naming the file and the dataset."""
    g = f[trial.group]
    where = f"{trial.file}: {trial.group}"

    def dataset(name: str, width: int | None) -> np.ndarray:
        """The dataset's values (T, width or 1) in its own integer dtype: checked against
        their range before any conversion (uint64 beyond int64 would wrap round)."""
        d = _node(g, name, f"{where}/")
        if not isinstance(d, h5py.Dataset):
            raise RecordingError(f"{where}/{name}: missing")
        shape = "(T,)" if width is None else f"(T, {width})"
        if d.ndim != (1 if width is None else 2) or (width is not None and d.shape[1] != width):
            raise RecordingError(f"{where}/{name}: shape {d.shape}, expected {shape}")
        if not np.issubdtype(d.dtype, np.integer):
            raise RecordingError(f"{where}/{name}: dtype {d.dtype}, expected integer counts")
        try:
            values = d[()]
        except (OSError, ValueError) as e:  # a damaged chunk, a compression filter missing
            why = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise RecordingError(f"{where}/{name}: cannot be read ({why})") from None
        return values.reshape(d.shape[0], width or 1)  # (T, 1) for a 1-D dataset, T = 0 too

    stamps = dataset("timestamps", None)[:, 0]
    if len(stamps) == 0:
        raise RecordingError(f"{where}/timestamps: no frames")
    odd = (stamps < FIRST_TIME) | (stamps > LAST_TIME)
    if odd.any():
        row = int(np.argmax(odd))
        raise RecordingError(f"{where}/timestamps: value {stamps[row]} at frame {row} is not a "
                             "time of 1970..2099 in whole Unix seconds")
    stamps = stamps.astype(np.int64)  # in range: exact
    _utc(where, int(stamps[0]))  # the take's recorded_utc: made here, in the checking pass
    columns = []
    for k in FINGERS:
        for name, width, _ in MODALITIES:
            path = f"finger_{k}/{name}"
            x = dataset(path, width)
            if len(x) != len(stamps):
                raise RecordingError(f"{where}/{path}: {len(x)} frames, but timestamps has "
                                     f"{len(stamps)}")
            bad = (x < 0) | (x > ADC_MAX)
            if bad.any():
                row, col = (int(v[0]) for v in np.nonzero(bad))
                raise RecordingError(f"{where}/{path}: value {x[row, col]} at frame {row} is "
                                     f"not a 12-bit count (0..{ADC_MAX})")
            columns.append(x.astype(np.int64))  # in range: exact
    return np.concatenate(columns, axis=1), stamps


def irregular(stamps: np.ndarray) -> str | None:
    """What is odd in a trial's timestamps (T,) Unix seconds, frame by frame: where they first
    go back, and where they first jump by more than a second (about 100 frames share a
    second). None when they are neither."""
    step = np.diff(stamps)
    said = []
    for odd, what in ((step < 0, "go back"), (step > 1, "jump")):
        rows = np.flatnonzero(odd)
        if rows.size:
            i = int(rows[0])
            times = "" if rows.size == 1 else f" (and {rows.size - 1} more)"
            said.append(f"{what} from {stamps[i]} to {stamps[i + 1]} at frame {i + 1}{times}")
    return "; ".join(said) or None


def _utc(where: str, seconds: int) -> str:
    """``seconds`` (Unix time) as ``YYYY-MM-DDTHH:MM:SSZ``; :class:`RecordingError` naming
    ``where`` (the file and trial) when this system's clock functions cannot convert it."""
    try:
        return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(seconds))
    except (OverflowError, OSError, ValueError) as e:
        raise RecordingError(f"{where}/timestamps: value {seconds} at frame 0 cannot be "
                             f"converted to a date here ({e})") from None


def _metadata(trial: Trial, stamps: np.ndarray) -> dict:
    return {
        "object": trial.label,
        "trial": trial.group,
        "pdc_setting": trial.pdc_setting,
        "depth": trial.depth,
        "repetition": trial.repetition,
        "user": trial.repetition,
        "recorded_utc": _utc(f"{trial.file}: {trial.group}", int(stamps[0])),
        "origin": ORIGIN + trial.file.name,
        "licence": LICENCE,
        "notes": "f<k>_pac_00..21 are the 22 vibration samples of each 10 ms frame in time "
                 "order (one 2.2 kHz signal); all values raw 12-bit ADC counts",
        "signals": signals(),
    }


def signals(fingers: tuple[int, ...] = FINGERS) -> dict[str, list[str]]:
    """The takes' high-rate signal declarations: ``f<k>_pac`` = the 22 vibration channels of
    finger k in time order (one 2.2 kHz signal at 100 frames/s)."""
    return {f"f{k}_pac": [f"f{k}_pac_{i:02d}" for i in range(PAC_SAMPLES)] for k in fingers}


def import_biotac(files: list[Path], out: Path, force: bool = False,
                  written: Callable[[Path], object] | None = None) -> list[Path]:
    """Write one take per trial of ``files`` into the dataset folder ``out``; returns the CSV
    paths. Everything is read and checked before the first take is written; takes of the same
    names already in ``out`` are refused, or replaced with ``force``. Timestamps that go back
    or jump (:func:`irregular`) are a ``warning:`` line on stderr per trial, before any take
    is written; the frames are imported in file order all the same. ``written(path)``, when
    given, is called as each take is whole."""
    files = [Path(p) for p in files]
    first: dict[Path, Path] = {}
    for p in files:  # the same file twice (under any spelling) would import its trials twice
        if p.resolve() in first:
            raise RecordingError(f"{p}: given twice (also as {first[p.resolve()]})")
        first[p.resolve()] = p
    handles = {p: _open(p) for p in files}
    try:
        trials: list[Trial] = []
        for p, f in handles.items():
            trials += _trials(p, f)
        seen: dict[str, Path] = {}
        for t in trials:
            if t.group in seen:
                raise RecordingError(f"{t.file}: trial {t.group} also in {seen[t.group]}")
            seen[t.group] = t.file
        for t in trials:  # check every trial (no data kept) before writing any
            odd = irregular(read_trial(handles[t.file], t)[1])
            if odd is not None:
                print(f"{command_prefix()}warning: {t.file}: {t.group}/timestamps: {odd} "
                      "(imported in file order)", file=sys.stderr, flush=True)
        # every input is valid: only now may --force delete the takes these replace
        out = dataset_folder(out)
        info = DeviceInfo(RATE_HZ, channels(), device="biotac-bolt")
        replace_takes(out, [t.group for t in trials], force, info)
        paths = []
        for t in trials:
            raw, stamps = read_trial(handles[t.file], t)
            with whole_take(out, t.group, force, done=written), TakeWriter(
                    out, t.label, info, f"biotac:{t.file.name}", name=t.group,
                    extra=_metadata(t, stamps), exact=True) as w:
                w.write(0, 0, raw)
            paths.append(w.csv_path)
        return paths
    finally:
        for f in handles.values():
            f.close()


__all__ = ["FINGERS", "FIRST_TIME", "LAST_TIME", "RATE_HZ", "Trial", "channels", "import_biotac",
           "irregular", "read_trial", "signals"]
