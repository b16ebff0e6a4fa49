"""The CSV line mode of the stream decoder: one sample per line, comma- or space-separated
plain decimal numbers, as a hobby board prints them (``device/PROTOCOL.md``, "CSV line mode").

A line is classified on its own (:func:`csv_kind`); :class:`CsvLines` is the part of
:class:`~tactile.device.protocol.decoder.StreamDecoder` that turns lines into samples once the
decoder has decided the stream is CSV. It holds no state of its own: it works on the decoder's
buffer, counters and ``_csv_*`` fields, which ``StreamDecoder.__init__`` sets.
"""

from __future__ import annotations

import math
import re

import numpy as np

from tactile.device.protocol.events import Event, Gap, Samples
from tactile.device.protocol.info import (
    FLOAT32_MAX,
    MAX_CHANNELS,
    MAX_NAME,
    ChannelSpec,
    DeviceInfo,
)

MAX_CSV_LINE = 4096  # bytes; a longer line without a newline is discarded
CSV_AGREE = 3  # readable CSV lines of one width in a row that decide the stream's width
CSV_HOLD = 64  # lines held at most while the CSV width is undecided
CSV_NAMES_WAIT_S = 2.0  # a stream opened mid-run: rows held this long for a names line...
CSV_NAMES_WAIT_MAX = 2048  # ... and at most this many lines
CSV_NAMES_WAIT_BYTES = 1 << 18  # ... of at most this many bytes (wide rows: bounded memory)
_RESTART = ("restart",)  # in the lines held for names: the link was re-opened here
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_./\-]*")
# Plain decimal numbers as a board prints them: sign, digits, point, exponent. Nothing else
# (no "1_0", "0x10", "inf", "nan", non-ASCII digits).
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


class CsvLines:
    """CSV lines -> :class:`Samples` (and a ``rejected`` :class:`Gap` for unreadable rows)."""

    def _feed_csv(self) -> list[Event]:
        events: list[Event] = []
        buf = self._buf
        start = 0
        while (end := buf.find(b"\n", max(start, self._scan))) >= 0:
            line = bytes(buf[start:end])
            start = end + 1
            if self._line_partial and len(line) <= MAX_CSV_LINE \
                    and csv_kind(line) not in (None, "skip") and csv_kind(line)[0] == "names":
                self._line_partial = False  # a names line as a board prints it at start-up
                self._on_line(line, events)
            elif self._line_partial:  # the line the port was opened in: a row may be cut
                self._line_partial = False
                self._csv_reject(len(line) + 1)
            elif len(line) > MAX_CSV_LINE:
                self._csv_reject(len(line) + 1)
            else:
                self._on_line(line, events)
        del buf[:start]
        if len(buf) > MAX_CSV_LINE:
            self._csv_reject(len(buf))
            buf.clear()
            self._line_partial = True  # what follows is the rest of that line
        self._scan = len(buf)
        return events

    def _csv_reject(self, nbytes: int) -> None:
        if self._csv_wait is not None:  # in its place among the rows held for names
            self._csv_wait.append((None, nbytes))
            return
        self.stats.csv_rejected += 1
        self.stats.bytes_discarded += nbytes
        if self.info is not None:  # before the first row, a bad line is not a lost sample
            self._csv_rejected_run += 1

    def _on_line(self, line: bytes, events: list[Event]) -> None:
        kind = csv_kind(line)
        if kind == "skip":
            return
        if self._csv_wait is not None:
            self._wait_line(kind, len(line) + 1, events)
            return
        if self._csv_width is not None:
            self._csv_line(kind, len(line) + 1, events)
            return
        # undecided: hold the line; CSV_AGREE readable lines of one width in a row decide it
        # (a names line may only open the run; unreadable lines do not break it)
        self._csv_held.append((kind, len(line) + 1))
        width, count = self._csv_run
        if kind is not None:
            what, w, _ = kind
            count = count + 1 if what == "row" and w == width else 1
            self._csv_run = width, count = w, count
        if count >= CSV_AGREE:
            self._csv_width = width
            held, self._csv_held = self._csv_held, []
            if self._mid_run and not any(k is not None and k[0] == "names" and k[1] == width
                                         for k, _ in held):
                self._csv_wait = held  # opened mid-run, no names yet: they may follow
                self._csv_wait_bytes = sum(n for _, n in held)
                return
            for k, nbytes in held:
                self._csv_line(k, nbytes, events)
        elif len(self._csv_held) > CSV_HOLD:
            self._csv_reject(self._csv_held.pop(0)[1])

    def _wait_line(self, kind, nbytes: int, events: list[Event]) -> None:
        """A line while the rows of a stream opened mid-run wait for a names line: one of the
        stream's width names them all (a board that repeats its names line, which the port
        opened after); after :data:`CSV_NAMES_WAIT_S` of rows (at the CSV rate, at most
        :data:`CSV_NAMES_WAIT_MAX` lines) they go on as ``ch0``, ``ch1``..."""
        if kind is not None and kind[0] == "names" and kind[1] == self._csv_width:
            self._csv_names = kind[2]
            self._release_wait(events)
            return  # (the line itself: the names just taken, so nothing)
        self._csv_wait.append((kind, nbytes))
        self._csv_wait_bytes += nbytes
        limit = min(max(CSV_HOLD, math.ceil(CSV_NAMES_WAIT_S * self.csv_rate_hz)),
                    CSV_NAMES_WAIT_MAX)
        if len(self._csv_wait) >= limit or self._csv_wait_bytes > CSV_NAMES_WAIT_BYTES:
            self._release_wait(events)

    def _release_wait(self, events: list[Event]) -> None:
        """The lines held for a names line, decoded in order (a re-opened link's ``restart``
        gap where it happened)."""
        held, self._csv_wait, self._csv_wait_bytes = self._csv_wait, None, 0
        for k, nbytes in held:
            if k is _RESTART:
                self._restart_pending = self.info is not None  # (before any row: no break)
            else:
                self._csv_line(k, nbytes, events)

    @property
    def waiting_info(self) -> DeviceInfo | None:
        """While the rows of a stream opened mid-run wait for a names line: the device they
        show so far (its width at the CSV rate, unnamed); else None. What a reopened port's
        probe compares (a CSV device is known by its width and rate, not its names)."""
        if self._csv_wait is None or self._csv_width is None:
            return None
        return DeviceInfo(self.csv_rate_hz, tuple(ChannelSpec(f"ch{i}", "")
                                                  for i in range(self._csv_width)), "csv")

    def finish(self) -> list[Event]:
        """The events of what is decoded but held back: the rows of a stream opened mid-run
        still waiting for a names line (then named ``ch0``, ``ch1``...). Call it when the
        stream ends (a recorder closing its take), so that no row is left undelivered."""
        events: list[Event] = []
        if self._csv_wait is not None:
            self._release_wait(events)
        return events

    def _csv_line(self, kind, nbytes: int, events: list[Event]) -> None:
        """One line once the width is decided."""
        if kind is None:
            self._csv_reject(nbytes)
            return
        what, width, values = kind
        if what == "names":
            if self.info is None and width == self._csv_width:  # the latest one before the
                self._csv_names = values  # first row names the channels
            elif self.info is None or values != self.info.channel_names:
                self._csv_reject(nbytes)
            # else the run's own names again (a board that restarted, or one that repeats
            # them): no sample, so not a rejected row that would count as one lost
            return
        if width != self._csv_width:
            self._csv_reject(nbytes)
            return
        if self.info is None:
            names = self._csv_names or tuple(f"ch{i}" for i in range(width))
            chans = tuple(ChannelSpec(n, "") for n in names)
            self._set_info(DeviceInfo(self.csv_rate_hz, chans, "csv"), events)
        host = self._host_next
        if self._restart_pending:  # the first row after a reconnection (StreamDecoder.reconnected)
            self._restart_pending = False
            self.stats.restarts += 1
            self.stats.gaps += 1
            events.append(Gap(host, 0, "restart"))
        if self._csv_rejected_run:
            missing = self._csv_rejected_run
            self._csv_rejected_run = 0
            host += missing
            self.stats.gaps += 1
            self.stats.samples_lost += missing
            events.append(Gap(host, missing, "rejected"))
        self._host_next = host + 1
        self.stats.csv_rows += 1
        self.stats.samples += 1
        t_us = round(host * 1e6 / self.info.sample_rate_hz)
        events.append(Samples(host, t_us, np.asarray([values], dtype=np.float64)))


def csv_kind(line: bytes):
    """Classify a CSV line: ``"skip"`` (blank/comment), ``None`` (unreadable),
    ``("row", width, values)`` or ``("names", width, names)``; width is 1..MAX_CHANNELS."""
    try:
        text = line.decode("ascii").strip()
    except UnicodeDecodeError:
        return None
    if not text or text.startswith("#"):
        return "skip"
    if "," in text:
        if text.count(",") >= MAX_CHANNELS:
            return None
        fields = [f.strip() for f in text.split(",")]
    else:
        fields = text.split()
        if len(fields) > MAX_CHANNELS:
            return None
    if all(_NUMBER.fullmatch(f) for f in fields):
        values = tuple(float(f) for f in fields)
        if not all(abs(v) <= FLOAT32_MAX for v in values):  # float32 overflow (1e39)
            return None  # never enters the pipeline (the model reads float32)
        return ("row", len(values), values)
    if all(len(f) <= MAX_NAME and _NAME.fullmatch(f) for f in fields) \
            and len(set(fields)) == len(fields):
        return ("names", len(fields), tuple(fields))
    return None


__all__ = ["CsvLines", "csv_kind", "MAX_CSV_LINE", "CSV_AGREE", "CSV_HOLD",
           "CSV_NAMES_WAIT_S", "CSV_NAMES_WAIT_MAX", "CSV_NAMES_WAIT_BYTES"]
