"""Import the HapMat recordings (a 6-axis IMU on a hand-held stick, 5 materials, 100 Hz) as takes
(``tactile-import-hapmat``).

The recordings come from https://github.com/henryyantq/haptic-kinematics (MIT licence), folder
``HapMat dataset``: one ``<Material> 1.csv`` per material with a ``time`` column (the suffix
in any case: ``Paper 1.CSV`` is read too).

Each material's 60 s session becomes one take labelled with the material in lower case. Channels
map onto the pen's names: ``accel_x..z`` from HapMat's accelerometer (g, gravity already
removed upstream) and ``gyro_x..z`` from its calibrated rotation rate ``rota_x..z``, converted
from rad/s to the pen's deg/s. The pen's ``pressure_0/1`` are absent (the stick has no tip
sensor) and listed as such in each take's metadata. Values are stored as float64, scale 1.

The bundled ``.npz`` holds the same: ``X`` (materials, samples, channels), ``classes`` (one name
per material), ``channels`` (one name per channel of ``X``), ``fs_hz`` (the rate, Hz). Every
input is checked before a take is replaced or written; what is not as described (arrays of other
shapes or lengths, a channel named twice, NaN or inf, a rate that is not one number in (0, 1e6]
Hz, a CSV's time column that does not rise evenly, a CSV column named twice), two materials that
would be one label (a name given twice, or names that differ only in case, ``Paper`` and
``paper``: one take per material) or a name that cannot be a label is one line naming the file,
exit code 1.
"""

from __future__ import annotations

import math
import re
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from tactile.contract_keys import MAX_RATE_HZ
from tactile.device.protocol.info import ChannelSpec, DeviceInfo
from tactile.device.recordings.reader import load_numbers
from tactile.device.recordings.take import (
    check_label,
    dataset_folder,
    replace_takes,
    whole_take,
)
from tactile.device.recordings.take_meta import class_key
from tactile.device.recordings.writer import TakeWriter
from tactile.errors import FrameError, RecordingError

CHANNELS = (
    ChannelSpec("accel_x", "g"),
    ChannelSpec("accel_y", "g"),
    ChannelSpec("accel_z", "g"),
    ChannelSpec("gyro_x", "deg/s"),
    ChannelSpec("gyro_y", "deg/s"),
    ChannelSpec("gyro_z", "deg/s"),
)
SOURCE_COLUMNS = ("accel_x", "accel_y", "accel_z", "rota_x", "rota_y", "rota_z")


def _first_twice(names: list[str]) -> str | None:
    """The first name that ``names`` gives a second time, or None."""
    return next((c for k, c in enumerate(names) if c in names[:k]), None)


def _read_npz(npz: Path) -> tuple[list[str], list[str], list[np.ndarray], float, str]:
    """The bundled form: ``X`` (material, sample, channel), ``classes`` (one name per material),
    ``channels`` (one name per channel), ``fs_hz``; optional ``source``. Returns the materials,
    how each is named in an error, their samples (n, 6) in :data:`SOURCE_COLUMNS` order, the
    rate and the origin."""
    try:
        with open(npz, "rb") as f:
            if f.read(4) != b"PK\x03\x04":  # numpy's own error advises unpickling it
                raise ValueError("not a .npz file: a .npz is a zip of numpy arrays")
        with np.load(npz, allow_pickle=False) as d:  # a zip: an NpzFile
            x, classes, channels, fs = d["X"], d["classes"], d["channels"], d["fs_hz"]
            origin = str(d["source"]) if "source" in d.files else "HapMat"
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise RecordingError(f"{npz}: not the HapMat .npz ({why})") from None
    if fs.ndim != 0 or fs.dtype.kind not in "iuf":
        raise RecordingError(f"{npz}: fs_hz is {fs.dtype} of shape {fs.shape}, expected one "
                             "number (the sample rate, Hz)")
    rate = float(fs)
    if not (math.isfinite(rate) and 0 < rate <= MAX_RATE_HZ):
        raise RecordingError(f"{npz}: fs_hz {rate:g}: the sample rate must be in "
                             f"(0, {MAX_RATE_HZ:g}] Hz")
    if x.ndim != 3 or x.dtype.kind not in "iuf":
        raise RecordingError(f"{npz}: X is {x.dtype} of shape {x.shape}, expected real numbers "
                             "of shape (materials, samples, channels)")
    if x.shape[0] == 0 or x.shape[1] == 0:
        raise RecordingError(f"{npz}: X of shape {x.shape} holds no samples")
    for key, names, axis, what in (("classes", classes, 0, "materials"),
                                   ("channels", channels, 2, "channels")):
        if names.ndim != 1 or names.dtype.kind != "U":
            raise RecordingError(f"{npz}: {key} is {names.dtype} of shape {names.shape}, "
                                 "expected a list of names (strings)")
        if len(names) != x.shape[axis]:
            raise RecordingError(f"{npz}: {key} has {len(names)} names for the "
                                 f"{x.shape[axis]} {what} of X {x.shape}")
    names = [str(c) for c in channels]
    twice = _first_twice(names)
    if twice is not None:
        raise RecordingError(f"{npz}: channels names {twice!r} twice")
    try:
        cols = [names.index(c) for c in SOURCE_COLUMNS]
    except ValueError:
        raise RecordingError(f"{npz}: channels {names} lack one of {SOURCE_COLUMNS}") from None
    materials = [str(c) for c in classes]
    shown = [f"classes[{k}] {c!r}" for k, c in enumerate(materials)]
    return materials, shown, [x[k][:, cols] for k in range(len(materials))], rate, origin


def _read_csv_folder(folder: Path) -> tuple[list[str], list[str], list[np.ndarray], float, str]:
    """The upstream form: a folder of ``<Material> 1.csv`` files (``HapMat dataset/``; ``.CSV``
    or any case of the suffix too), each with a header ``time,accel_x,...,rota_z`` (each column
    once) and one row per sample; the rate is that of the time column (seconds), which rises in
    even steps."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".csv" and p.is_file())
    if not files:
        raise RecordingError(f"{folder}: no .csv files (expected the HapMat dataset folder)")
    classes, series, rates = [], [], []
    for f in files:
        # a spreadsheet's export may start with a UTF-8 byte-order mark and pad the names
        with open(f, encoding="utf-8-sig", errors="replace") as fh:
            header = [c.strip() for c in fh.readline().split(",")]
        twice = _first_twice(header)
        if twice is not None:  # which of the two would be the data?
            raise RecordingError(f"{f}: column {twice!r} appears twice in the header")
        missing = [c for c in ("time", *SOURCE_COLUMNS) if c not in header]
        if missing:
            raise RecordingError(f"{f}: not a HapMat recording (no column {missing[0]!r})")
        try:
            table = load_numbers(f, skiprows=1)
        except ValueError as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise RecordingError(f"{f}: unreadable rows ({msg})") from None
        if len(table) < 2:
            raise RecordingError(f"{f}: fewer than 2 data rows")
        if table.shape[1] != len(header):
            raise RecordingError(f"{f}: rows of {table.shape[1]} values under a header of "
                                 f"{len(header)} columns")
        t = table[:, header.index("time")]
        step = np.diff(t)
        if not np.all(step > 0):
            i = int(np.argmin(step > 0))  # the first step that is not > 0 (NaN included)
            raise RecordingError(f"{f}: time column does not rise ({t[i]:g} then {t[i + 1]:g} "
                                 f"at line {i + 3})")
        if not np.allclose(step, step.mean(), rtol=0.01, atol=1e-6):
            raise RecordingError(f"{f}: time column is not evenly spaced")
        classes.append(re.sub(r"\s+\d+$", "", f.stem))  # "Paper 1" -> "Paper"
        series.append(table[:, [header.index(c) for c in SOURCE_COLUMNS]])
        rates.append(1.0 / step.mean())
    if max(rates) - min(rates) > 1e-3 * max(rates):
        found = ", ".join(f"{c} {r:g} Hz" for c, r in zip(classes, rates))
        raise RecordingError(f"{folder}: the files' sample rates differ ({found})")
    rate = round(float(np.mean(rates)), 6)
    return (classes, [repr(f.name) for f in files], series, rate,
            "HapMat (haptic-kinematics repository, CSV files)")


def _labels(source: Path, materials: list[str], shown: list[str]) -> list[str]:
    """The takes' labels, each material in lower case; :class:`RecordingError` naming
    ``source`` and the material (``shown``) when one cannot be a label, or when two would be
    one class (:func:`class_key`: ``Paper`` and ``paper``, a name given twice): one take per
    material, never two of one label."""
    labels: list[str] = []
    seen: dict[str, str] = {}
    for material, what in zip(materials, shown):
        try:
            label = check_label(material.lower())
        except RecordingError as e:
            raise RecordingError(f"{source}: {what}: {e}") from None
        key = class_key(label)
        if key in seen:
            raise RecordingError(f"{source}: more than one recording of one material: "
                                 f"{seen[key]} and {what} (one take per material; names that "
                                 "differ only in case or Unicode form are one class)")
        seen[key] = what
        labels.append(label)
    return labels


def import_hapmat(source: Path, out: Path, force: bool = False,
                  written: Callable[[Path], object] | None = None) -> list[Path]:
    """Write one take per material (``hapmat-<material>``) from the bundled ``.npz`` or the
    upstream folder of CSVs; returns the CSV paths. Takes of those names already in ``out`` are
    refused, or replaced with ``force``. ``written(path)``, when given, is called as each
    take is whole."""
    source = Path(source)
    if not source.exists():
        raise RecordingError(f"{source}: no such file or folder (give the 'HapMat dataset' "
                             "folder of CSV files or hapmat_stick_imu.npz)")
    if source.is_dir():
        classes, shown, series, rate, origin = _read_csv_folder(source)
    else:
        classes, shown, series, rate, origin = _read_npz(source)
    labels = _labels(source, classes, shown)
    try:
        info = DeviceInfo(rate, CHANNELS, device="hapmat-stick-imu")
    except FrameError as e:  # a device's error (exit code 2); here the input file's
        raise RecordingError(f"{source}: {e}") from None
    to_deg = np.array([1, 1, 1, 180 / math.pi, 180 / math.pi, 180 / math.pi])
    takes = []  # every input checked before any take is replaced or written
    for material, label, x in zip(classes, labels, series):
        values = x.astype(np.float64) * to_deg  # (n, 6)
        if not np.all(np.isfinite(values)):
            raise RecordingError(f"{source}: {material} holds NaN or inf")
        takes.append((label, values))
    out = dataset_folder(out)
    replace_takes(out, [f"hapmat-{label}" for label, _ in takes], force, info)
    paths = []
    for label, values in takes:
        extra = {
            "absent_channels": ["pressure_0", "pressure_1"],
            "origin": origin,
            "licence": "MIT (HapMat, haptic-kinematics repository)",
            "user": 0,
            "notes": "accel has gravity removed upstream; gyro from rota_* (rad/s -> deg/s)",
        }
        name = f"hapmat-{label}"
        with whole_take(out, name, force, done=written), TakeWriter(
                out, label, info, f"hapmat:{source.name}", name=name, extra=extra,
                exact=True) as w:
            w.write(0, 0, values)
        paths.append(w.csv_path)
    return paths


__all__ = ["CHANNELS", "SOURCE_COLUMNS", "import_hapmat"]
