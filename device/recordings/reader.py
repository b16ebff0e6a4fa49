"""Reading takes back: one (:func:`read_take`) or a dataset folder (:func:`load_dataset`).

Everything wrong with a take (a key of its JSON, a row of its CSV) is a
:class:`~tactile.errors.RecordingError` naming the file and the place.
"""

from __future__ import annotations

import math
import os
import re
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from tactile.cli import prefix
from tactile.device.protocol.info import DeviceInfo
from tactile.device.recordings.take import FIXED_COLUMNS, GAP_LINE, Take, _why, header_cell
from tactile.device.recordings.take_meta import FORMAT, class_key, read_meta
from tactile.errors import RecordingError


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
        k = next((i for i, (a, b) in enumerate(zip(columns, expected)) if a != b),
                 min(len(columns), len(expected)))
        here = _cell(columns[k]) if k < len(columns) else "missing"
        there = _cell(expected[k]) if k < len(expected) else "no column there"
        raise RecordingError(f"{csv_path}: its header does not match the metadata's channels: "
                             f"column {k + 1} is {here}, the metadata says {there} ("
                             f"{len(columns)} column{'s' * (len(columns) != 1)}, the "
                             f"metadata {len(expected)})")
    if "columns" in meta and meta["columns"] != columns:  # the writer's own record of them
        k = next((i for i, (a, b) in enumerate(zip(columns, meta["columns"])) if a != b),
                 min(len(columns), len(meta["columns"])))
        raise RecordingError(f"{csv_path}: key 'columns' differs from the CSV's header at "
                             f"column {k + 1} ({len(meta['columns'])} names, the header "
                             f"{len(columns)}): one of the pair was edited")
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
    _check_range(csv_path, table, info, integer and n > 0)
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
    mismatch = _mismatch(meta, n, int(seq[-1]) if n else None, truncated)
    return Take(csv_path, meta, info, seq, t_us, raw.reshape(n, c), truncated, mismatch)


COUNT_LIMIT = 2**53
"""The largest count an integer take holds: past it a CSV number is not read exactly."""


def _check_range(csv_path: Path, table: np.ndarray, info: DeviceInfo, integer: bool) -> None:
    """Every value fits where it goes: an integer take's counts read exactly (at most
    :data:`COUNT_LIMIT`), and every value in units (count x scale + offset) within float32's
    range, as the runtime's windows hold them and the wire protocol allows. The first row that
    does not is an error naming it (one channel at a time: no copy of the whole table)."""
    top, first = float(np.finfo(np.float32).max), None
    for k, ch in enumerate(info.channels):
        col = table[:, 2 + k]
        for bad, what in ((np.abs(col) > COUNT_LIMIT if integer else None,
                           "a count beyond 2^53 (not read exactly)"),
                          (np.abs(col * ch.scale + ch.offset) > top,
                           "a value beyond float32's range (3.4e38) in its unit")):
            if bad is not None and bad.any():
                row = int(np.flatnonzero(bad)[0])
                if first is None or row < first[0]:
                    first = (row, what, ch.name, col[row])
    if first is not None:
        row, what, name, v = first
        raise RecordingError(f"{csv_path}: data row {row + 1} holds {what}: {name} = {v:g}")


def _mismatch(meta: dict, rows: int, last: int | None, truncated: bool) -> str | None:
    """What the CSV holds against what the JSON of a take its writer closed (``complete``)
    counts, when they differ (rows lost or added after recording: a copy cut short, an edit);
    else None."""
    if meta.get("complete") is not True or "samples" not in meta:
        return None
    want, want_last = meta["samples"], meta.get("last_seq")
    if rows == want and not truncated and (want_last is None or last == want_last):
        return None
    held = f"{rows} samples" + (f" up to seq {last}" if last is not None else "")
    cut = " and half a row" if truncated else ""
    said = f"{want}" + (f" up to seq {want_last}" if want_last is not None else "")
    return (f"holds {held}{cut} where its JSON says the finished take had {said}: rows were "
            "lost or added after recording")


def _cell(text: str, most: int = 60) -> str:
    """A header cell for an error line, cut to ``most`` characters (a file that is no take
    may have a whole line there)."""
    return repr(text) if len(text) <= most else repr(text[:most]) + f"... ({len(text)} chars)"


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


_SAID: set[tuple[str, Path]] = set()  # (what, file): the warnings said in this process


def say_mismatch(take: Take) -> None:
    """Name on stderr, once per process, a finished take whose CSV holds other rows than its
    JSON counts (``Take.mismatch``): one ``warning:`` line after the running command's name,
    nothing for a take whose counts agree."""
    if take.mismatch and ("mismatch", take.path) not in _SAID:
        _SAID.add(("mismatch", take.path))
        print(f"{prefix()}warning: {take.path}: {take.mismatch}", file=sys.stderr, flush=True)


def _a_takes_json(path: Path) -> bool:
    """Whether ``path`` begins as a take's JSON does (its format named in the first bytes):
    a run's metrics.json in a sub-folder is not a take's."""
    try:
        with open(path, "rb") as f:
            return f'"{FORMAT}"'.encode() in f.read(256)
    except OSError:
        return False


def say_orphans(folder: str | os.PathLike) -> None:
    """Name on stderr, once per process, the ``.csv`` files of ``folder`` that have no
    ``.json`` beside them, and the takes' ``.json`` files that have no ``.csv``: a take whose
    JSON (or CSV) was lost (a copy that missed it) is not read, and no take is left out
    without a word."""
    for ext, other, what in ((".csv", ".json", "not read as a take"),
                             (".json", ".csv", "no samples: not read as a take")):
        orphans = sorted(p for p in Path(folder).rglob(f"*{ext}")
                         if not p.with_suffix(other).is_file() and ("orphan", p) not in _SAID
                         and (ext == ".csv" or _a_takes_json(p)))
        if orphans:
            _SAID.update(("orphan", p) for p in orphans)
            more = f" and {len(orphans) - 3} more" if len(orphans) > 3 else ""
            print(f"{prefix()}warning: {', '.join(str(p) for p in orphans[:3])}{more}: a {ext} "
                  f"without its {other}, {what}", file=sys.stderr, flush=True)


def load_dataset(folder: str | os.PathLike) -> list[Take]:
    """Every take in ``folder``; raises if there is none or if channel layouts disagree. A
    finished take whose CSV holds other rows than its JSON counts (``Take.mismatch``) is
    named on stderr, once per process, whichever command reads it."""
    takes = [read_take(p) for p in iter_takes(folder)]
    say_orphans(folder)
    if not takes:
        raise RecordingError(f"{folder}: no takes (.csv + .json pairs) found")
    seen: dict[str, Path] = {}
    for t in takes:  # runs name their split's takes by file name (sub-folders are allowed)
        if t.path.name in seen:
            raise RecordingError(f"{folder}: two takes named {t.path.name} ({seen[t.path.name]} "
                                 f"and {t.path}): rename one (a dataset's take names differ)")
        seen[t.path.name] = t.path
    by_case: dict[str, Take] = {}
    for t in takes:  # 'Paper' and 'paper' would train as two classes of one surface
        other = by_case.setdefault(class_key(t.label), t)
        if other.label != t.label:
            raise RecordingError(
                f"{folder}: labels {other.label!r} ({other.path.name}) and {t.label!r} "
                f"({t.path.name}) differ only in case (or Unicode form): they would be two "
                "classes; give both takes one spelling (the 'label' of the take's .json)")
    for t in takes:
        say_mismatch(t)
    first = takes[0]
    for t in takes[1:]:
        if t.channels != first.channels or not math.isclose(
            t.info.sample_rate_hz, first.info.sample_rate_hz
        ):
            raise RecordingError(
                f"{t.path}: channels/rate {t.channels}@{t.info.sample_rate_hz} Hz differ from "
                f"{first.path}: {first.channels}@{first.info.sample_rate_hz} Hz"
            )
        for a, b in zip(t.info.channels, first.info.channels):
            if a.unit != b.unit:  # values in units are mixed only in one unit
                raise RecordingError(f"{t.path}: {a.name} is in {a.unit!r}, in {first.path} "
                                     f"in {b.unit!r}")
    say_copies(takes)
    return takes


def copies(takes: list[Take]) -> list[tuple[int, int]]:
    """Pairs (i, j), i > j, of takes that hold the same recording under two names (a copied
    take), j the first of its kind in ``takes``' order. Only takes of one label and length are
    fingerprinted, so most datasets cost little or no hashing."""
    alike: dict[tuple, list[int]] = {}
    for i, t in enumerate(takes):
        alike.setdefault((t.label, len(t.seq), t.raw.shape), []).append(i)
    pairs = []
    for group in (g for g in alike.values() if len(g) > 1):
        by_print: dict[str, int] = {}
        for i in group:
            j = by_print.setdefault(takes[i].fingerprint(), i)
            if j != i:
                pairs.append((i, j))
    return sorted(pairs)


def say_copies(takes: list[Take]) -> None:
    """Name on stderr, once per process, takes that hold the same recording under two names
    (:func:`copies`: read twice, it can land in training and in test)."""
    for i, j in copies(takes):
        t, other = takes[i], takes[j]
        if ("copy", t.path) not in _SAID:
            _SAID.add(("copy", t.path))
            print(f"{prefix()}warning: {t.path}: the same recording as {other.path} "
                  "(label, samples and times): it is read twice", file=sys.stderr, flush=True)


__all__ = ["copies", "iter_takes", "load_dataset", "load_numbers", "read_take", "say_mismatch"]
