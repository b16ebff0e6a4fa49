"""Recordings: one take per file pair, a dataset is a folder of them.

A take is ``NAME.csv`` (what the pen sent, one row per sample, columns ``seq,t_us,<channels>``,
raw counts exactly as received) plus ``NAME.json`` beside it (label, channel names, units,
scales, rate, device header, start time, source, the gaps the decoder saw and its counters).
Both open in any text editor or spreadsheet. ``value_in_unit = raw * scale + offset``.

The writer appends and flushes the CSV at least once a second and rewrites the JSON atomically
at the same time, so a recorder killed at any moment leaves a readable take that lost at most the
last second. A take the writer closed cleanly says ``"complete": true``.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tactile.device.decoder import DecoderStats, Gap
from tactile.device.info import DeviceInfo
from tactile.errors import RecordingError

FORMAT = "tactile-recording"
VERSION = 1
FIXED_COLUMNS = ("seq", "t_us")


@dataclass
class Take:
    """One recording read back.

    ``raw`` is (n, channels) as stored (int64 for integer data, float64 otherwise); ``seq`` and
    ``t_us`` are (n,) int64. ``gaps`` lists the decoder's gap events as dicts.
    """

    path: Path
    meta: dict
    info: DeviceInfo
    seq: np.ndarray
    t_us: np.ndarray
    raw: np.ndarray
    truncated: bool = False  # the last line was cut (the writer was killed mid-write)

    @property
    def label(self) -> str:
        return self.meta["label"]

    @property
    def channels(self) -> tuple[str, ...]:
        return self.info.channel_names

    def values(self) -> np.ndarray:
        """(n, channels) float64 in the channels' units."""
        scale = np.array([c.scale for c in self.info.channels])
        offset = np.array([c.offset for c in self.info.channels])
        return self.raw * scale + offset

    def segments(self) -> list[tuple[int, int]]:
        """Row ranges [start, stop) with no gap inside: split at seq jumps and recorded gaps."""
        if len(self.seq) == 0:
            return []
        cuts = set(np.flatnonzero(np.diff(self.seq) != 1) + 1)
        where = {int(s): i for i, s in enumerate(self.seq)}
        for g in self.meta.get("gaps", []):
            if g["seq"] in where and where[g["seq"]] > 0:
                cuts.add(where[g["seq"]])
        bounds = [0, *sorted(cuts), len(self.seq)]
        return [(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


# A label names the take's files and a class; these are refused by FAT/exFAT cards (a board's
# usual storage) or break the CSV/JSON pair: / \ : * ? " < > | , control characters.
_LABEL_BAD = re.compile(r'[/\\:*?"<>|,\x00-\x1f\x7f]')
LABEL_RULE = ("1-64 characters, not starting with '.' or a space, none of "
              "/ \\ : * ? \" < > | , tab or newline")


def check_label(label: str) -> str:
    """``label`` if it can name a class and a take's files anywhere, else :class:`RecordingError`
    stating :data:`LABEL_RULE`."""
    if (not isinstance(label, str) or not 1 <= len(label) <= 64 or label != label.strip()
            or label.startswith(".") or _LABEL_BAD.search(label)):
        raise RecordingError(f"label {label!r}: must be {LABEL_RULE}")
    return label


def dataset_folder(folder: str | os.PathLike) -> Path:
    """``folder`` as a dataset folder to write takes into, created if missing (with its parents);
    :class:`RecordingError` naming it when it is a file or cannot be made."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise RecordingError(f"{folder}: not a folder (takes are written into a dataset folder)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RecordingError(f"{folder}: cannot make the dataset folder ({e.strerror})") from None
    return folder


def replace_takes(folder: Path, stems: list[str], force: bool) -> None:
    """Before a command writes takes named ``stems`` into ``folder``: if any exists, refuse
    (:class:`RecordingError` naming the first, the command neither overwrites nor duplicates a
    dataset by being run twice) or, with ``force``, delete them."""
    found = [p for s in stems for p in (folder / f"{s}.csv", folder / f"{s}.json") if p.exists()]
    if found and not force:
        more = f" and {len(found) - 1} more files" if len(found) > 1 else ""
        raise RecordingError(f"{found[0]}{more} already exist: choose another folder, or "
                             "--force to replace them")
    for p in found:
        p.unlink()


class TakeWriter:
    """Writes one take; use as a context manager or call :meth:`close`.

    Args:
        folder: dataset folder (created if missing).
        label: the class of this take (e.g. ``paper``).
        info: the device header the samples belong to.
        source: where the data came from (port URL, file...), kept in the metadata.
        name: file stem; default ``<label>-<UTC time>``, made unique in the folder.
        extra: more metadata (e.g. ``{"session": 3}``).
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        label: str,
        info: DeviceInfo,
        source: str = "",
        name: str | None = None,
        extra: dict | None = None,
        flush_every_s: float = 1.0,
    ) -> None:
        check_label(label)
        self.folder = dataset_folder(folder)
        started = time.gmtime()
        stem = name or f"{label}-{time.strftime('%Y%m%dT%H%M%SZ', started)}"
        self.csv_path = _unique(self.folder, stem)
        self.json_path = self.csv_path.with_suffix(".json")
        self.info = info
        self.meta = {
            "format": FORMAT,
            "version": VERSION,
            "label": label,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", started),
            "source": source,
            "device": info.to_dict(),
            "columns": [*FIXED_COLUMNS, *info.channel_names],
            "samples": 0,
            "first_seq": None,
            "last_seq": None,
            "gaps": [],
            "decoder": {},
            "complete": False,
            **(extra or {}),
        }
        self._flush_every = flush_every_s
        self._last_flush = time.monotonic()
        self._csv = open(self.csv_path, "w", encoding="ascii", newline="\n")  # noqa: SIM115
        self._csv.write(",".join(self.meta["columns"]) + "\n")
        self.flush()

    def write(self, seq: int, t_us: int, raw: np.ndarray) -> None:
        """Append samples (n, channels) starting at ``seq`` with device time ``t_us``."""
        raw = np.asarray(raw)
        if raw.ndim != 2 or raw.shape[1] != len(self.info.channels):
            raise RecordingError(
                f"samples of shape {raw.shape} do not fit {len(self.info.channels)} channels"
            )
        if self.meta["last_seq"] is not None and seq <= self.meta["last_seq"]:
            raise RecordingError(f"seq {seq} after {self.meta['last_seq']}: samples out of order")
        n = len(raw)
        t = t_us + np.round(np.arange(n) * (1e6 / self.info.sample_rate_hz)).astype(np.int64)
        seqs = np.arange(seq, seq + n, dtype=np.int64)
        buf = io.StringIO()
        if np.issubdtype(raw.dtype, np.integer):
            np.savetxt(buf, np.column_stack([seqs, t, raw.astype(np.int64)]), "%d", ",")
        else:  # repr round-trips a float64 exactly
            for s, ti, row in zip(seqs, t, raw.tolist(), strict=True):
                buf.write(f"{s},{ti},{','.join(map(repr, row))}\n")
        self._csv.write(buf.getvalue())
        if self.meta["first_seq"] is None:
            self.meta["first_seq"] = seq
        self.meta["last_seq"] = seq + len(raw) - 1
        self.meta["samples"] += len(raw)
        self._maybe_flush()

    def gap(self, gap: Gap) -> None:
        self.meta["gaps"].append({"seq": gap.seq, "missing": gap.missing, "reason": gap.reason})
        self._maybe_flush()

    def set_decoder_stats(self, stats: DecoderStats) -> None:
        self.meta["decoder"] = stats.as_dict()

    def _maybe_flush(self) -> None:
        if time.monotonic() - self._last_flush >= self._flush_every:
            self.flush()

    def flush(self) -> None:
        """Make everything written so far durable and readable."""
        self._csv.flush()
        os.fsync(self._csv.fileno())
        tmp = self.json_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.meta, indent=1) + "\n")
        os.replace(tmp, self.json_path)
        self._last_flush = time.monotonic()

    def close(self) -> None:
        if self._csv.closed:
            return
        self.meta["complete"] = True
        self.flush()
        self._csv.close()

    def __enter__(self) -> TakeWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _unique(folder: Path, stem: str) -> Path:
    path = folder / f"{stem}.csv"
    k = 1
    while path.exists() or path.with_suffix(".json").exists():
        k += 1
        path = folder / f"{stem}-{k}.csv"
    return path


def read_take(path: str | os.PathLike) -> Take:
    """Read a take from its ``.csv`` or ``.json`` path. Raises :class:`RecordingError`."""
    path = Path(path)
    if path.is_dir():
        raise RecordingError(f"{path}: a folder, not a take (give the take's .csv file)")
    if path.suffix not in (".csv", ".json"):
        raise RecordingError(f"{path}: not a take (give the take's .csv file)")
    csv_path, json_path = path.with_suffix(".csv"), path.with_suffix(".json")
    for p in (csv_path, json_path):
        if not p.is_file():
            raise RecordingError(f"{p}: missing (a take is a .csv with a .json beside it)")
    try:
        meta = json.loads(json_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise RecordingError(f"{json_path}: not valid JSON ({e})") from None
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise RecordingError(
            f"{json_path}: not a {FORMAT} v{VERSION} file "
            f"(format={meta.get('format')!r}, version={meta.get('version')!r})"
        )
    try:
        info = DeviceInfo.from_dict(meta["device"])
        label = meta["label"]
    except (KeyError, TypeError, ValueError) as e:
        raise RecordingError(f"{json_path}: bad device or label ({e})") from None
    if not isinstance(label, str) or not label:
        raise RecordingError(f"{json_path}: label must be a non-empty string")
    with open(csv_path, "rb") as f:
        f.readline()  # the header (its names hold an "e")
        # values written from counts have no decimal point and no exponent
        integer = not any(_DECIMAL.search(chunk) for chunk in iter(lambda: f.read(1 << 20), b""))
        size = f.tell()
        f.seek(max(size - 1, 0))
        truncated = size > 0 and f.read(1) != b"\n"  # a killed writer's half line at the end
    c = len(info.channels)
    with open(csv_path, encoding="ascii", errors="replace", newline="") as f:
        head = f.readline().rstrip("\r\n")
        columns = head.split(",") if head else []
        expected = [*FIXED_COLUMNS, *info.channel_names]
        if columns != expected:
            raise RecordingError(
                f"{csv_path}: columns {columns} do not match the metadata {expected}")
        # numpy's C parser straight from the file: a few bytes a value in memory (a long take
        # must replay on a small board); an unreadable row is then found and named
        try:
            whole = (line for line in f if line.endswith("\n"))  # only the last is cut
            table = load_numbers(whole, comments=None)
        except ValueError:
            raise RecordingError(f"{csv_path}: {_first_bad_row(csv_path, c + 2)}") from None
    n = len(table)
    if n and table.shape[1] != c + 2:
        raise RecordingError(f"{csv_path}: rows of {table.shape[1]} values, expected {c + 2}")
    table = table.reshape(n, c + 2)
    if n and not np.all(np.isfinite(table)):  # before any cast to integers
        raise RecordingError(f"{csv_path}: holds NaN or inf values")
    seq, t_us = table[:, 0].astype(np.int64), table[:, 1].astype(np.int64)
    if n and not (np.array_equal(seq, table[:, 0]) and np.array_equal(t_us, table[:, 1])):
        raise RecordingError(f"{csv_path}: seq and t_us must be integers")
    integer = integer and n > 0
    raw = table[:, 2:].astype(np.int64) if integer else table[:, 2:]
    if n and np.any(np.diff(seq) <= 0):
        bad = int(np.flatnonzero(np.diff(seq) <= 0)[0]) + 2
        raise RecordingError(f"{csv_path}: seq not increasing at data row {bad}")
    return Take(csv_path, meta, info, seq, t_us, raw.reshape(n, c), truncated)


_DECIMAL = re.compile(rb"[.eE]")


def load_numbers(source, **kwargs) -> np.ndarray:
    """``np.loadtxt`` of comma-separated numbers as a (rows, columns) float64 table; no rows is
    an empty table, without numpy's "input contained no data" warning. ``ValueError`` on an
    unreadable row, as numpy raises it."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return np.loadtxt(source, delimiter=",", ndmin=2, dtype=np.float64, **kwargs)


def _first_bad_row(csv_path: Path, width: int) -> str:
    """What is wrong with the first unreadable data row (the error path only)."""
    with open(csv_path, encoding="ascii", errors="replace") as f:
        f.readline()
        for k, line in enumerate(f, start=1):
            fields = line.rstrip("\r\n").split(",")
            if line.strip() == "":
                continue
            if len(fields) != width:
                return f"data row {k} (line {k + 1}) has {len(fields)} values, expected {width}"
            for v in fields:
                try:
                    float(v)
                except ValueError:
                    return f"data row {k} (line {k + 1}): {v!r} is not a number"
    return "unreadable rows"


def iter_takes(folder: str | os.PathLike) -> Iterator[Path]:
    """The ``.csv`` files of the takes in a dataset folder (recursively), sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RecordingError(f"{folder}: not a folder")
    return iter(sorted(p for p in folder.rglob("*.csv") if p.with_suffix(".json").is_file()))


def load_dataset(folder: str | os.PathLike) -> list[Take]:
    """Every take in ``folder``; raises if there is none or if channel layouts disagree."""
    takes = [read_take(p) for p in iter_takes(folder)]
    if not takes:
        raise RecordingError(f"{folder}: no takes (.csv + .json pairs) found")
    first = takes[0]
    for t in takes[1:]:
        if t.channels != first.channels or not math.isclose(
            t.info.sample_rate_hz, first.info.sample_rate_hz
        ):
            raise RecordingError(
                f"{t.path}: channels/rate {t.channels}@{t.info.sample_rate_hz} Hz differ from "
                f"{first.path}: {first.channels}@{first.info.sample_rate_hz} Hz"
            )
    return takes
