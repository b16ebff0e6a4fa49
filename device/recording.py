"""Recordings: one take per file pair, a dataset is a folder of them.

A take is ``NAME.csv`` (what the pen sent, one row per sample, columns ``seq,t_us,<channels>``,
raw counts exactly as received, and a ``# gap ...`` line wherever the stream broke) plus
``NAME.json`` beside it (label, channel names, units, scales, rate, device header, start time,
source, a copy of the gaps and the decoder's counters). Both open in any text editor or
spreadsheet. ``value_in_unit = raw * scale + offset``.

The CSV is append-only and written through: every row and gap line reaches the file in stream
order the moment it is written, so a recorder killed at any moment leaves a prefix of the stream
that knows every gap inside it. A clock (not the next write) fsyncs it and rewrites the JSON
atomically at least once a second. A take the writer closed cleanly says ``"complete": true``.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import threading
import time
import unicodedata
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tactile.device.decoder import DecoderStats, Gap
from tactile.device.info import DeviceInfo
from tactile.device.take_meta import FORMAT, VERSION, read_meta
from tactile.errors import ConfigError, RecordingError

FIXED_COLUMNS = ("seq", "t_us")
GAP_LINE = re.compile(r"# gap seq=(\d+) missing=(\d+) reason=([a-z_]+)\n")
_REASON = re.compile(r"[a-z_]+")


@dataclass
class Take:
    """One recording read back.

    ``raw`` is (n, channels) as stored (int64 for integer data, float64 otherwise); ``seq`` and
    ``t_us`` are (n,) int64. ``meta["gaps"]`` lists every gap the take knows (its CSV's gap
    lines and the JSON's copy) as dicts ``seq``, ``missing``, ``reason``, and ``row``: the index
    of the first row after the gap.
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

    def fingerprint(self) -> str:
        """The take's identity by content: 16 hex digits of the SHA-256 of its label, channel
        names, sequence numbers, timestamps and raw samples. Two folders holding takes of the
        same names but other recordings give other fingerprints (training records those of its
        test takes, so that evaluation and export recognise the test split by content)."""
        h = hashlib.sha256()
        h.update(repr((str(self.label), tuple(self.channels))).encode())
        for a in (self.seq, self.t_us, self.raw):
            arr = np.ascontiguousarray(a)
            h.update(f"{arr.dtype.str}{arr.shape}".encode())
            h.update(arr.tobytes())
        return h.hexdigest()[:16]

    def segments(self) -> list[tuple[int, int]]:
        """Row ranges [start, stop) with no gap inside: split at seq jumps and recorded gaps."""
        if len(self.seq) == 0:
            return []
        cuts = set((np.flatnonzero(np.diff(self.seq) != 1) + 1).tolist())
        for g in self.meta.get("gaps", []):
            row = g.get("row")
            if row is None:  # a gap known by its seq only: before the first row at or after it
                row = int(np.searchsorted(self.seq, g["seq"]))
            if 0 < row < len(self.seq):
                cuts.add(int(row))
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


def header_cell(name: str) -> str:
    """A channel name as a CSV header cell: on one line, without a separator.

    ``,``, ``"``, ``#``, ``%``, control characters and any space but U+0020 become ``%XX`` of
    their UTF-8 bytes (``a,b`` -> ``a%2Cb``); everything else, non-ASCII letters included, stays
    as it is. The JSON keeps the names themselves."""
    out = []
    for ch in name:
        if ch in ',"#%' or (unicodedata.category(ch)[0] in "CZ" and ch != " "):
            out.append("".join(f"%{b:02X}" for b in ch.encode("utf-8", "surrogatepass")))
        else:
            out.append(ch)
    return "".join(out)


def _write_all(fd: int, data: bytes) -> None:
    """``os.write`` until all of ``data`` is written (a regular file may take part of it)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _replace_file(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (a temporary file, fsynced, then renamed)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        try:
            _write_all(fd, text.encode("utf-8"))
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise


class TakeWriter:
    """Writes one take; use as a context manager or call :meth:`close`.

    Every :meth:`write` and :meth:`gap` goes to the CSV at once, in order (nothing waits in a
    buffer of this process); a background clock fsyncs the CSV and rewrites the JSON every
    ``flush_every_s`` seconds while there is something new, data or not. An ``OSError`` (a full
    disk) becomes a :class:`RecordingError` naming the file; the take then keeps what was
    written and is never marked complete.

    Args:
        folder: dataset folder (created if missing).
        label: the class of this take (e.g. ``paper``).
        info: the device header the samples belong to.
        source: where the data came from (port URL, file...), kept in the metadata.
        name: file stem; default ``<label>-<UTC time>``, made unique in the folder.
        extra: more metadata (e.g. ``{"session": 3}``).
        flush_every_s: period of the clock, seconds.
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
        if not (isinstance(flush_every_s, int | float) and 0 < flush_every_s < math.inf):
            raise ConfigError(f"flush_every_s {flush_every_s!r}: must be a positive number")
        self.folder = dataset_folder(folder)
        started = time.gmtime()
        stem = name or f"{label}-{time.strftime('%Y%m%dT%H%M%SZ', started)}"
        self.info = info
        columns = [*FIXED_COLUMNS, *(header_cell(n) for n in info.channel_names)]
        self.meta = {
            "format": FORMAT,
            "version": VERSION,
            "label": label,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", started),
            "source": source,
            "device": info.to_dict(),
            "columns": columns,
            "samples": 0,
            "first_seq": None,
            "last_seq": None,
            "gaps": [],
            "decoder": {},
            "complete": False,
            **(extra or {}),
        }
        self._lock = threading.Lock()  # the CSV's end and self.meta
        self._flush_lock = threading.Lock()  # one flush at a time
        self._error: str | None = None  # set by the first failed write: the take is frozen
        self._told = False  # whether a caller has been raised that error
        self._dirty = True
        self.flushes = 0
        self.csv_path, self._fd = _create(self.folder, stem)
        self.json_path = self.csv_path.with_suffix(".json")
        try:
            self._append((",".join(columns) + "\n").encode("utf-8"), self.csv_path)
            self.flush()
        except RecordingError:  # nothing usable was made: leave nothing behind
            os.close(self._fd)
            for p in (self.csv_path, self.json_path):
                p.unlink(missing_ok=True)
            raise
        self._stop = threading.Event()
        self._clock = threading.Thread(target=self._tick, args=(flush_every_s,), daemon=True,
                                       name=f"flush {self.csv_path.name}")
        self._clock.start()

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
        if n == 0:
            return
        t = t_us + np.round(np.arange(n) * (1e6 / self.info.sample_rate_hz)).astype(np.int64)
        seqs = np.arange(seq, seq + n, dtype=np.int64)
        buf = io.StringIO()
        if np.issubdtype(raw.dtype, np.integer):
            np.savetxt(buf, np.column_stack([seqs, t, raw.astype(np.int64)]), "%d", ",")
        else:  # repr round-trips a float64 exactly
            for s, ti, row in zip(seqs, t, raw.tolist(), strict=True):
                buf.write(f"{s},{ti},{','.join(map(repr, row))}\n")
        with self._lock:
            self._append(buf.getvalue().encode("ascii"), self.csv_path)
            if self.meta["first_seq"] is None:
                self.meta["first_seq"] = seq
            self.meta["last_seq"] = seq + n - 1
            self.meta["samples"] += n
            self._dirty = True

    def gap(self, gap: Gap) -> None:
        """Record a gap before the next row: a ``# gap`` line in the CSV, and in the JSON."""
        if not _REASON.fullmatch(gap.reason):
            raise RecordingError(f"gap reason {gap.reason!r}: must be lowercase letters or _")
        line = f"# gap seq={int(gap.seq)} missing={int(gap.missing)} reason={gap.reason}\n"
        with self._lock:
            self._append(line.encode("ascii"), self.csv_path)
            self.meta["gaps"].append(
                {"seq": int(gap.seq), "missing": int(gap.missing), "reason": gap.reason})
            self._dirty = True

    def set_decoder_stats(self, stats: DecoderStats) -> None:
        with self._lock:
            self.meta["decoder"] = stats.as_dict()
            self._dirty = True

    def _append(self, data: bytes, path: Path) -> None:
        """Write ``data`` at the CSV's end (caller holds the lock, or is the constructor)."""
        if self._error:
            self._raise()
        try:
            _write_all(self._fd, data)
        except OSError as e:
            self._error = f"{path}: cannot write ({_why(e)}); the take keeps what came before"
            self._raise()

    def _tick(self, period: float) -> None:
        while not self._stop.wait(period):
            if self._dirty and not self._error:
                try:
                    self._flush()
                except RecordingError:  # kept in self._error: the next call raises it
                    pass

    def flush(self) -> None:
        """Make everything written so far durable, and the JSON up to date."""
        try:
            self._flush()
        except RecordingError:
            self._told = True
            raise

    def _raise(self) -> None:
        self._told = True
        raise RecordingError(self._error) from None

    def _flush(self) -> None:
        with self._flush_lock:
            with self._lock:
                if self._error:
                    raise RecordingError(self._error)
                meta = {**self.meta, "gaps": list(self.meta["gaps"])}
                self._dirty = False
            try:
                os.fsync(self._fd)
            except OSError as e:
                with self._lock:
                    self._error = f"{self.csv_path}: cannot write ({_why(e)})"
                raise RecordingError(self._error) from None
            try:
                _replace_file(self.json_path, json.dumps(meta, indent=1) + "\n")
            except OSError as e:
                with self._lock:
                    self._error = f"{self.json_path}: cannot write ({_why(e)})"
                raise RecordingError(self._error) from None
            self.flushes += 1

    def close(self, complete: bool = True) -> None:
        """Stop the clock; mark the take complete (unless ``complete`` is False, or a write
        failed). Raises
        :class:`RecordingError` if this last flush fails, or if the clock's flush failed and
        no call has raised that yet (a failure already raised is not raised again)."""
        if self._fd < 0:
            return
        self._stop.set()
        self._clock.join()
        try:
            if self._error is None:
                with self._lock:
                    self.meta["complete"] = complete
                self.flush()
            elif not self._told:
                self._raise()
        finally:
            os.close(self._fd)
            self._fd = -1

    @property
    def error(self) -> str | None:
        """Why the take stopped taking data (a failed write), or None."""
        return self._error

    def __enter__(self) -> TakeWriter:
        return self

    def __exit__(self, kind, *exc) -> None:
        self.close(complete=kind is None)  # a block that raised did not finish the take


def _why(e: OSError) -> str:
    return e.strerror or str(e) or type(e).__name__


def _create(folder: Path, stem: str) -> tuple[Path, int]:
    """A new ``.csv`` named after ``stem`` (``-2``, ``-3``... if taken), opened exclusively."""
    k = 1
    while True:
        path = folder / (f"{stem}.csv" if k == 1 else f"{stem}-{k}.csv")
        if not path.with_suffix(".json").exists():
            try:
                return path, os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                pass
            except OSError as e:
                raise RecordingError(f"{path}: cannot create ({_why(e)})") from None
        k += 1


# -- reading ---------------------------------------------------------------------------------------


def read_take(path: str | os.PathLike) -> Take:
    """Read a take from its ``.csv`` or ``.json`` path. Raises :class:`RecordingError` naming
    the file (and the key or the row) for anything wrong with it."""
    path = Path(path)
    if path.is_dir():
        raise RecordingError(f"{path}: a folder, not a take (give the take's .csv file)")
    if path.suffix not in (".csv", ".json"):
        raise RecordingError(f"{path}: not a take (give the take's .csv file)")
    csv_path, json_path = path.with_suffix(".csv"), path.with_suffix(".json")
    for p in (csv_path, json_path):
        if not p.is_file():
            raise RecordingError(f"{p}: missing (a take is a .csv with a .json beside it)")
    meta, info = read_meta(json_path)
    try:
        return _read_rows(csv_path, meta, info)
    except OSError as e:
        raise RecordingError(f"{csv_path}: cannot read ({_why(e)})") from None


def _read_rows(csv_path: Path, meta: dict, info: DeviceInfo) -> Take:
    c = len(info.channels)
    with open(csv_path, "rb") as f:
        head = f.readline()
        # values written from counts have no decimal point and no exponent (gap lines aside);
        # chunks end at a line's end so that a line is never seen in two halves
        integer = True
        while chunk := f.read(1 << 20):
            chunk += f.readline()
            integer = integer and not _DECIMAL.search(chunk)
        size = f.tell()
        f.seek(max(size - 1, 0))
        truncated = size > len(head) and f.read(1) != b"\n"  # a killed writer's half line
    try:
        head_text = head.decode("utf-8").rstrip("\r\n")
    except UnicodeDecodeError:
        raise RecordingError(f"{csv_path}: its header line is not UTF-8 text") from None
    columns = head_text.split(",") if head_text else []
    expected = [*FIXED_COLUMNS, *(header_cell(n) for n in info.channel_names)]
    if columns != expected:
        raise RecordingError(f"{csv_path}: columns {_shown_list(columns)} do not match the "
                             f"metadata {_shown_list(expected)}")
    gaps: list[dict] = []
    rows = 0

    def data_lines(f):  # the rows for numpy; gap lines noted with the row they come before
        nonlocal rows
        for k, line in enumerate(f, start=2):
            if not line.endswith("\n"):  # only the last line can be cut
                continue
            if line.startswith("#"):
                m = GAP_LINE.fullmatch(line)
                if not m:
                    raise RecordingError(f"{csv_path}: line {k} is not a gap line "
                                         f"(# gap seq=N missing=N reason=word): {line[:60]!r}")
                gaps.append({"seq": int(m[1]), "missing": int(m[2]), "reason": m[3],
                             "row": rows})
            elif line.strip():
                rows += 1
                yield line

    with open(csv_path, encoding="ascii", errors="replace", newline="") as f:
        f.readline()
        # numpy's C parser over the file's lines: a few bytes a value in memory (a long take
        # must replay on a small board); an unreadable row is then found and named
        try:
            table = load_numbers(data_lines(f), comments=None)
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
    # the CSV's gap lines are the record; the JSON's copy can only lag behind them (a take of
    # version 1 has only the copy): every gap in either is kept
    seen = {(g["seq"], g["missing"], g["reason"]) for g in gaps}
    for g in meta.get("gaps", []):
        if (g["seq"], g["missing"], g["reason"]) not in seen:
            gaps.append({"seq": g["seq"], "missing": g["missing"], "reason": g["reason"],
                         "row": int(np.searchsorted(seq, g["seq"]))})
    meta = {**meta, "gaps": sorted(gaps, key=lambda g: g["row"])}
    return Take(csv_path, meta, info, seq, t_us, raw.reshape(n, c), truncated)


def _shown_list(items: list[str]) -> str:
    text = repr(items)
    return text if len(text) <= 200 else text[:197] + "..."


_DECIMAL = re.compile(rb"^[^#\n]*[.eE]", re.MULTILINE)


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
        k = 0  # data rows, gap lines aside
        for number, line in enumerate(f, start=2):
            if line.strip() == "" or line.startswith("#"):
                continue
            k += 1
            fields = line.rstrip("\r\n").split(",")
            if len(fields) != width:
                return f"data row {k} (line {number}) has {len(fields)} values, expected {width}"
            for v in fields:
                try:
                    float(v)
                except ValueError:
                    return f"data row {k} (line {number}): {v[:40]!r} is not a number"
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
