"""Writing a take (:class:`TakeWriter`; the format: :mod:`~tactile.device.recordings.take`).

The CSV is append-only and written through: every row and gap line reaches the file in stream
order the moment it is written, so a recorder killed at any moment leaves a prefix of the stream
that knows every gap inside it. A clock (not the next write) fsyncs it and rewrites the JSON
atomically at least once a second. A take the writer closed cleanly says ``"complete": true``.
"""

from __future__ import annotations

import io
import json
import math
import os
import threading
import time
from pathlib import Path

import numpy as np

from tactile.device.protocol.events import DecoderStats, Gap
from tactile.device.protocol.info import DeviceInfo
from tactile.device.recordings.take import (
    _REASON,
    FIXED_COLUMNS,
    KEPT,
    TakeExists,
    _why,
    check_label,
    dataset_folder,
    header_cell,
)
from tactile.device.recordings.take_meta import FORMAT, VERSION
from tactile.errors import ConfigError, RecordingError
from tactile.files import replace_file
from tactile.files import write_all as _write_all


def _replace_file(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (:func:`tactile.files.replace_file`)."""
    replace_file(path, text.encode("utf-8"))


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
        exact: the take is named ``name`` or not written (:class:`TakeExists`): a derived
            take (an import, a simulated take) whose name the command checked.
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
        exact: bool = False,
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
        self.csv_path, self._fd = _create(self.folder, stem, exact)
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
            self._error = f"{path}: cannot write ({_why(e)}){KEPT}"
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


def _create(folder: Path, stem: str, exact: bool = False) -> tuple[Path, int]:
    """A new ``.csv`` named after ``stem`` (``-2``, ``-3``... if taken; with ``exact``, that
    name or :class:`TakeExists`), opened exclusively."""
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
        if exact:
            raise TakeExists(f"{path}: written since the folder was checked (another program "
                             "writing there?): choose another folder")
        k += 1


__all__ = ["TakeWriter"]
