"""The take format: one take per file pair, a dataset is a folder of them.

A take is ``NAME.csv`` (what the pen sent, one row per sample, columns ``seq,t_us,<channels>``,
raw counts exactly as received, and a ``# gap ...`` line wherever the stream broke) plus
``NAME.json`` beside it (label, channel names, units, scales, rate, device header, start time,
source, a copy of the gaps and the decoder's counters). Both open in any text editor or
spreadsheet. ``value_in_unit = raw * scale + offset``.

This module holds what a take is (:class:`Take`, read back) and the rules its names follow (labels,
dataset folders, CSV header cells); :mod:`~tactile.device.recordings.writer` writes takes and
:mod:`~tactile.device.recordings.reader` reads them.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import unicodedata
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tactile.device.protocol.info import DeviceInfo
from tactile.device.recordings.take_meta import LABEL_RULE, check_label, class_key, read_meta
from tactile.errors import RecordingError

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
    # a finished take (``complete``) whose CSV holds other rows than its JSON counts: what
    # differs, for a warning (rows lost or added after recording); None when they agree
    mismatch: str | None = None

    @property
    def label(self) -> str:
        return self.meta["label"]

    @property
    def channels(self) -> tuple[str, ...]:
        return self.info.channel_names

    @property
    def declared_signals(self) -> tuple[tuple[str, tuple[str, ...]], ...]:
        """The high-rate signals the take's JSON declares, (name, channels in time order) in
        its order: what two takes must agree on to be read alike."""
        return tuple((k, tuple(v)) for k, v in (self.meta.get("signals") or {}).items())

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


def replace_takes(folder: Path, stems: list[str], force: bool,
                  info: DeviceInfo | None = None) -> None:
    """Before a command writes takes named ``stems`` into ``folder``: if any exists, refuse
    (:class:`RecordingError` naming the first, the command neither overwrites nor duplicates a
    dataset by being run twice) or, with ``force``, leave them to :func:`whole_take`, which
    replaces each when its new take is whole (so that a command stopped half-way leaves every
    take, old or new, whole). With ``info`` (the new takes' device), a folder whose other takes
    have other channels, units or another rate is refused too: the takes would make a dataset
    no command can read; so is a folder with a take of one of those names in a sub-folder, or
    one put aside by a replacing run that was killed (``NAME.csv.replaced``), even with
    ``force``."""
    if info is not None:
        check_joins(folder, set(stems), info)
    names = set(stems)  # a dataset's readers refuse two takes (.csv + .json) of one name
    deeper = min((p.with_suffix(".csv") for p in folder.rglob("*.json") if p.stem in names
                  and p.parent != folder and p.with_suffix(".csv").is_file()), default=None)
    if deeper is not None:
        raise RecordingError(f"{deeper}: a take of that name in a sub-folder of {folder} (a "
                             "dataset's takes need names of their own): choose another folder")
    aside = next(((s, p) for s in dict.fromkeys(stems) for p in (
        folder / f"{s}.csv{ASIDE}", folder / f"{s}.json{ASIDE}") if p.exists()), None)
    if aside:  # left by a replacing run that was killed: maybe the only whole copy of a take
        s, p = aside
        raise RecordingError(f"{p}: left by a run that was replacing take {s} with --force and "
                             f"was killed: if {s}.csv is missing or cut short (tactile-data "
                             f"says so), move the {ASIDE} files back in its place, else delete "
                             "them; then run again")
    found = [p for s in dict.fromkeys(stems)  # a name given twice is one take's files
             for p in (folder / f"{s}.csv", folder / f"{s}.json") if p.exists()]
    if found and not force:
        more = f" and {len(found) - 1} more files" if len(found) > 1 else ""
        raise RecordingError(f"{found[0]}{more} already exist: choose another folder, or "
                             "--force to replace them")


KEPT = "; the take keeps what came before"  # a recorder's take, after a write that failed


class TakeExists(RecordingError):
    """A take of the exact name a derived take must have (``TakeWriter(exact=True)``) is
    there: another program wrote it meanwhile."""


ASIDE = ".replaced"  # a take being replaced, while its new one is written (whole_take)


@contextlib.contextmanager
def whole_take(folder: Path, stem: str, replace: bool = False,
               done: Callable[[Path], object] | None = None) -> Iterator[None]:
    """Around the writing of one take that a command derives (an import, a simulated take),
    by a :class:`~tactile.device.recordings.writer.TakeWriter` named ``stem`` with ``exact``:
    when the writing stops half-way (Ctrl-C, a full disk), the take's files are removed, so
    that the folder holds whole takes only (a recorder's take, which holds what was recorded,
    is kept instead), and the writer's error says so. With ``replace`` (``--force``, which
    :func:`replace_takes` allowed), a take of that name already there is moved aside
    (``NAME.csv.replaced``) while the new one is written, put back when the writing stops
    half-way, and deleted once the new take is whole; without, one that has appeared since
    is refused. ``done(csv path)``: called once the new take is whole. The moves, the clean-up
    and ``done`` hold Ctrl-C and SIGTERM until they end (:func:`tactile.cli.holding_signals`):
    no take is left half moved, and a take that stays is one ``done`` was told of."""
    from tactile.cli import holding_signals

    paths = [folder / f"{stem}{suffix}" for suffix in (".csv", ".json")]
    aside: list[tuple[Path, Path]] = []
    try:
        with holding_signals():  # (a signal held here is raised as the block ends: below)
            for path in paths:
                if path.exists():
                    if not replace:
                        raise RecordingError(f"{path}: written since the folder was checked "
                                             "(another program writing there?): choose "
                                             "another folder, or --force to replace it")
                    old = path.with_name(path.name + ASIDE)
                    os.replace(path, old)
                    aside.append((old, path))
    except BaseException:
        with holding_signals():
            _put_back(aside)
        raise
    try:
        yield
    except TakeExists as e:  # another program's take has the name: its files stay, ours too
        kept = f"; the take it was to replace waits as {aside[0][0].name}" if aside else ""
        raise RecordingError(f"{e}{kept}") from None
    except BaseException as e:
        with contextlib.suppress(KeyboardInterrupt):  # the error, not a Ctrl-C meanwhile, is
            with holding_signals():  # what the command ends with (its files are in order)
                removed = False
                for path in paths:
                    removed |= path.exists()
                    path.unlink(missing_ok=True)
                _put_back(aside)
        if removed and isinstance(e, RecordingError):  # a write, or the data, refused
            kept = "the take it was to replace is kept" if aside else "the take is removed"
            raise RecordingError(str(e).removesuffix(KEPT) + f"; {kept} (the folder keeps "
                                 "whole takes only)") from None
        raise
    with holding_signals():
        for old, _ in aside:
            old.unlink()
        if done is not None:
            done(paths[0])


def _put_back(aside: list[tuple[Path, Path]]) -> None:
    """The files :func:`whole_take` moved aside, back under their names."""
    for old, path in aside:
        os.replace(old, path)


def check_joins(folder: Path, stems: set[str], info: DeviceInfo) -> None:
    """:class:`RecordingError` naming ``folder``, one of its takes and the first difference
    when the takes there (but those named ``stems``) have other channels, units or another
    rate than ``info``."""
    other = next((p for p in sorted(folder.rglob("*.json")) if p.stem not in stems
                  and p.with_suffix(".csv").is_file()), None)
    if other is None:
        return
    _, have = read_meta(other)
    why = _difference(have, info)
    if why:
        raise RecordingError(f"{folder}: holds takes of another device ({other.name}: {why}): "
                             "a dataset's takes share channels, units and rate; choose another "
                             "folder")


def check_label_joins(folder: Path, label: str) -> None:
    """:class:`RecordingError` when a take in ``folder`` spells ``label``'s class another way
    (``paper`` there, ``Paper`` here): the folder's readers refuse one class spelled two ways,
    so such a take would leave a folder that no command reads. A JSON that cannot be read is
    left to the readers, which name it."""
    if not folder.is_dir():
        return
    key = class_key(label)
    for p in sorted(folder.rglob("*.json")):
        if not p.with_suffix(".csv").is_file():
            continue
        try:
            other = json.loads(p.read_text(encoding="utf-8")).get("label")
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(other, str) and other != label and class_key(other) == key:
            raise RecordingError(f"{folder}: holds takes labelled {other!r} ({p.name}), the "
                                 f"label {label!r} but for case (or Unicode form): one class, "
                                 f"which a dataset spells one way; record it as {other!r}")


def _difference(have: DeviceInfo, info: DeviceInfo) -> str | None:
    """The first way the takes of ``info`` differ from a take of ``have``, in words."""
    theirs, mine = have.channel_names, info.channel_names
    if len(theirs) != len(mine):
        return f"{len(theirs)} channels, these takes {len(mine)}"
    for a, b in zip(have.channels, info.channels):
        if a.name != b.name:
            return f"channel {a.name!r} where these takes have {b.name!r}"
        if a.unit != b.unit:
            return f"{a.name} in {a.unit!r}, these takes in {b.unit!r}"
    if abs(info.sample_rate_hz - have.sample_rate_hz) > 1e-6 * max(
            info.sample_rate_hz, have.sample_rate_hz):
        return f"{have.sample_rate_hz:g} Hz, these takes {info.sample_rate_hz:g} Hz"
    return None


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


def _why(e: OSError) -> str:
    return e.strerror or str(e) or type(e).__name__


__all__ = ["FIXED_COLUMNS", "GAP_LINE", "LABEL_RULE", "Take", "TakeExists", "check_label",
           "dataset_folder", "header_cell", "replace_takes"]
