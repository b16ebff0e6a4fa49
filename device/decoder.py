"""The stream decoder: bytes in, samples and events out.

A pure state machine with no I/O (pyserial's ``Packetizer`` idea): call :meth:`StreamDecoder.feed`
with whatever bytes arrived and get back a list of events in stream order. It

* recognises binary frames (``device/PROTOCOL.md``) or CSV lines automatically;
* never raises on bad bytes: garbage, CRC failures and malformed frames are skipped and counted;
* resynchronises within one frame: a frame whose leading delimiter was lost, or that has garbage
  glued in front of it, is still recovered (see :func:`_valid_suffix_starts`);
* never invents or reorders samples: duplicates are dropped, overlaps trimmed, gaps reported with
  their size, and a device restart is reported as a gap;
* keeps a bounded buffer (at most one maximal frame plus one read).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from tactile.device.info import FLOAT32_MAX, ChannelSpec, DeviceInfo
from tactile.device.protocol import (
    MAX_ENCODED,
    SEQ_MODULO,
    HeaderFrame,
    SamplesFrame,
    cobs_decode,
    crc16,
    parse_body,
)
from tactile.errors import ConfigError

MAX_CSV_LINE = 4096  # bytes; a longer line without a newline is discarded
AUTO_PENDING = 8192  # bytes held while the decoder is still deciding binary vs CSV
_HALF = SEQ_MODULO // 2
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_./\-]*$")

Mode = Literal["auto", "binary", "csv"]


@dataclass(frozen=True)
class Samples:
    """A run of consecutive samples.

    ``seq`` is the host's sequence number of the first sample: the device's counter unwrapped
    past 2**32 and kept continuous across device restarts. ``t_us`` is the device clock at the
    first sample, unwrapped (in CSV mode, which has no device clock, it is derived from ``seq``
    and the configured rate). ``raw`` is (n, channels): int16 counts from binary frames,
    float64 values from CSV lines.
    """

    seq: int
    t_us: int
    raw: np.ndarray


@dataclass(frozen=True)
class Header:
    """The device described itself; ``changed`` is True when it differs from the previous one."""

    info: DeviceInfo
    changed: bool = False


@dataclass(frozen=True)
class Gap:
    """Samples that should have come before ``seq`` and did not.

    ``reason`` is ``"drop"`` (the device's sequence jumped: ``missing`` samples lost),
    ``"restart"`` (the device's sequence went back: it rebooted; ``missing`` is unknown, 0) or
    ``"rejected"`` (``missing`` CSV rows were unreadable). No window may span a gap.
    """

    seq: int
    missing: int
    reason: str


Event = Samples | Header | Gap


@dataclass
class DecoderStats:
    """Counters of everything the decoder saw and everything it dropped."""

    bytes_in: int = 0
    frames: int = 0  # good frames of any type
    samples: int = 0  # samples delivered
    header_frames: int = 0
    header_changes: int = 0
    crc_errors: int = 0  # chunks that unstuffed cleanly but failed the CRC
    malformed: int = 0  # chunks that are not valid COBS, or frames with an invalid structure
    bytes_discarded: int = 0  # bytes that belonged to no good frame or row
    duplicates: int = 0  # frames dropped because their samples were already delivered
    gaps: int = 0
    samples_lost: int = 0
    restarts: int = 0
    csv_rows: int = 0
    csv_rejected: int = 0
    extra: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "extra"}
        d.update(self.extra)
        return d

    @property
    def errors(self) -> int:
        return self.crc_errors + self.malformed + self.csv_rejected


def _valid_suffix_starts(chunk: bytes) -> list[int]:
    """Offsets ``i > 0`` where ``chunk[i:]`` is a well-formed COBS encoding, ascending.

    A COBS encoding is a chain of code bytes, each pointing at the next, that lands exactly on the
    end. Computed right to left in one pass, so trying every possible frame start after a
    corruption costs one CRC per candidate, not one decode per byte.
    """
    n = len(chunk)
    ok = bytearray(n + 1)
    ok[n] = 1
    for i in range(n - 1, 0, -1):
        j = i + chunk[i]
        if chunk[i] and j <= n and ok[j]:
            ok[i] = 1
    return [i for i in range(1, n - 2) if ok[i]]


class StreamDecoder:
    """Incremental decoder for one device stream.

    Args:
        mode: ``"auto"`` (default: decide from the bytes), ``"binary"`` or ``"csv"``.
        csv_rate_hz: sample rate assumed for CSV streams (they carry none).
        replay_window: a sequence number that goes back by at most this many samples is a
            duplicate (dropped); further back means the device restarted.
    """

    def __init__(
        self, mode: Mode = "auto", csv_rate_hz: float = 100.0, replay_window: int = 256
    ) -> None:
        if mode not in ("auto", "binary", "csv"):
            raise ConfigError(f"decoder mode {mode!r}: must be one of auto, binary, csv")
        if not (math.isfinite(csv_rate_hz) and csv_rate_hz > 0):
            raise ConfigError(f"csv rate {csv_rate_hz!r} Hz: must be a positive number")
        self.mode: Mode = mode
        self.csv_rate_hz = float(csv_rate_hz)
        self.replay_window = int(replay_window)
        self.stats = DecoderStats()
        self.info: DeviceInfo | None = None
        self._buf = bytearray()
        # sequence state: next expected device seq (u32) and host seq (unbounded int)
        self._dev_next: int | None = None
        self._host_next = 0
        self._t_last: int | None = None  # last device time seen, u32
        self._t_host = 0  # unwrapped device time of the last frame
        self._restart_pending = False  # set by reconnected()
        # csv state
        self._csv_names: tuple[str, ...] | None = None
        self._csv_rejected_run = 0

    # -- public ------------------------------------------------------------------------------------

    def feed(self, data: bytes) -> list[Event]:
        """Consume ``data`` (any length, any split) and return the events it completes."""
        self.stats.bytes_in += len(data)
        self._buf += data
        if self.mode == "auto":
            self.mode = self._detect()
            if self.mode == "auto":
                if len(self._buf) > AUTO_PENDING:  # bounded: forget the oldest half
                    cut = len(self._buf) - AUTO_PENDING // 2
                    self.stats.bytes_discarded += cut
                    del self._buf[:cut]
                return []
        if self.mode == "binary":
            return self._feed_binary()
        return self._feed_csv()

    def reconnected(self) -> None:
        """The link was re-opened: drop partial bytes and expect the device to have restarted.

        The next samples frame is then reported after a ``restart`` gap whatever its sequence
        number, since a pen that was unplugged rebooted and counts from 0 again.
        """
        self.stats.bytes_discarded += len(self._buf)
        self._buf.clear()
        if self._dev_next is not None:
            self._dev_next = None
            self._restart_pending = True

    @property
    def next_seq(self) -> int:
        """Host sequence number the next sample will get (if nothing is lost)."""
        return self._host_next

    # -- detection ---------------------------------------------------------------------------------

    def _detect(self) -> Mode:
        buf = bytes(self._buf)
        chunks = buf.split(b"\x00")[:-1]
        if any(self._parse_chunk(c)[0] is not None for c in chunks if c):
            return "binary"
        prev = None  # two readable lines of equal width in a row (names then row, or rows)
        for line in buf.split(b"\n")[:-1]:
            kind = _csv_kind(line)
            if kind == "skip":
                continue
            if kind is not None and prev is not None and kind[0] == "row" and prev[1] == kind[1]:
                return "csv"
            prev = kind
        return "auto"

    # -- binary ------------------------------------------------------------------------------------

    def _parse_chunk(self, chunk: bytes) -> tuple[SamplesFrame | HeaderFrame | None, int, str]:
        """Best frame in ``chunk``: (frame or None, bytes skipped before it, failure kind)."""
        decoded = cobs_decode(chunk)
        failure = "malformed"
        if decoded is not None and len(decoded) >= 3:
            body = decoded[:-2]
            if crc16(body) == int.from_bytes(decoded[-2:], "little"):
                parsed = parse_body(body)
                if parsed is not None:
                    return parsed, 0, ""
            else:
                failure = "crc"
        for start in _valid_suffix_starts(chunk):
            decoded = cobs_decode(chunk[start:])
            if decoded is None or len(decoded) < 3:
                continue
            body = decoded[:-2]
            if crc16(body) == int.from_bytes(decoded[-2:], "little"):
                parsed = parse_body(body)
                if parsed is not None:
                    return parsed, start, failure
        return None, len(chunk), failure

    def _feed_binary(self) -> list[Event]:
        events: list[Event] = []
        buf = self._buf
        start = 0
        while True:
            end = buf.find(b"\x00", start)
            if end < 0:
                break
            chunk = bytes(buf[start:end])
            start = end + 1
            if not chunk:
                continue
            if len(chunk) > MAX_ENCODED:  # only the tail can hold a frame
                self.stats.bytes_discarded += len(chunk) - MAX_ENCODED
                self.stats.malformed += 1
                chunk = chunk[-MAX_ENCODED:]
            parsed, skipped, failure = self._parse_chunk(chunk)
            if skipped:
                self.stats.bytes_discarded += skipped
                if failure == "crc":
                    self.stats.crc_errors += 1
                else:
                    self.stats.malformed += 1
            if parsed is not None:
                self._on_frame(parsed, events)
        del buf[:start]
        if len(buf) > MAX_ENCODED:  # no delimiter in sight: keep only what could be a frame
            cut = len(buf) - MAX_ENCODED
            self.stats.bytes_discarded += cut
            del buf[:cut]
        return events

    def _on_frame(self, parsed: SamplesFrame | HeaderFrame, events: list[Event]) -> None:
        if isinstance(parsed, HeaderFrame):
            self.stats.frames += 1
            self.stats.header_frames += 1
            self._set_info(parsed.info, events)
            return
        raw = parsed.raw
        if self.info is not None and raw.shape[1] != len(self.info.channels):
            # CRC-valid but contradicts the header: trust neither, drop it visibly
            self.stats.malformed += 1
            return
        self.stats.frames += 1
        n = raw.shape[0]
        if self._restart_pending:  # first frame after a reconnection
            self._restart_pending = False
            host = self._restart(events)
            self._t_host += self._dt(parsed.t_us)
        elif self._dev_next is None:  # first frame: host seq starts at the device's count
            host = parsed.seq
            self._t_host = parsed.t_us
        else:
            diff = (parsed.seq - self._dev_next) % SEQ_MODULO
            if diff < _HALF:  # forward: in order, or a drop of `diff` samples
                host = self._host_next + diff
                if diff:
                    self.stats.gaps += 1
                    self.stats.samples_lost += diff
                    events.append(Gap(host, diff, "drop"))
            else:
                back = SEQ_MODULO - diff
                if back <= self.replay_window:
                    if back >= n:  # all of it was delivered already
                        self.stats.duplicates += 1
                        return
                    # overlap (a re-sent frame split differently): keep only the unseen tail
                    raw = raw[back:]
                    n = raw.shape[0]
                    host = self._host_next
                    period = round(1e6 / self.info.sample_rate_hz) if self.info else 0
                    parsed = SamplesFrame(
                        (parsed.seq + back) % SEQ_MODULO,
                        (parsed.t_us + back * period) % SEQ_MODULO,
                        raw,
                    )
                else:  # the device rebooted
                    host = self._restart(events)
            self._t_host += self._dt(parsed.t_us)
        self._t_last = parsed.t_us
        self._dev_next = (parsed.seq + n) % SEQ_MODULO
        self._host_next = host + n
        self.stats.samples += n
        events.append(Samples(host, self._t_host, raw))

    def _restart(self, events: list[Event]) -> int:
        """The device restarted: continue the host count, mark the break, forget its clock."""
        self.stats.restarts += 1
        self.stats.gaps += 1
        events.append(Gap(self._host_next, 0, "restart"))
        self._t_last = None
        return self._host_next

    def _dt(self, t_us: int) -> int:
        if self._t_last is None:  # restart: no relation to the old clock; advance one period
            rate = self.info.sample_rate_hz if self.info else self.csv_rate_hz
            return round(1e6 / rate)
        return (t_us - self._t_last) % SEQ_MODULO

    def _set_info(self, info: DeviceInfo, events: list[Event]) -> None:
        if self.info is None:
            self.info = info
            events.append(Header(info, changed=False))
        elif info != self.info:
            self.stats.header_changes += 1
            self.info = info
            events.append(Header(info, changed=True))

    # -- csv ---------------------------------------------------------------------------------------

    def _feed_csv(self) -> list[Event]:
        events: list[Event] = []
        buf = self._buf
        start = 0
        while True:
            end = buf.find(b"\n", start)
            if end < 0:
                break
            line = bytes(buf[start:end])
            start = end + 1
            if len(line) > MAX_CSV_LINE:
                self._csv_reject(len(line))
                continue
            self._on_line(line, events)
        del buf[:start]
        if len(buf) > MAX_CSV_LINE:
            self._csv_reject(len(buf))
            buf.clear()
        return events

    def _csv_reject(self, nbytes: int) -> None:
        self.stats.csv_rejected += 1
        self.stats.bytes_discarded += nbytes
        if self.info is not None:  # before the first row, a bad line is not a lost sample
            self._csv_rejected_run += 1

    def _on_line(self, line: bytes, events: list[Event]) -> None:
        kind = _csv_kind(line)
        if kind == "skip":
            return
        if kind is None:
            self._csv_reject(len(line) + 1)
            return
        what, width, values = kind
        if what == "names":
            if self.info is None:  # before the first row: the latest names line wins
                self._csv_names = values
            else:
                self._csv_reject(len(line) + 1)
            return
        if self.info is None:
            names = self._csv_names
            if names is not None and len(names) != width:
                names = None  # a names line that does not fit the data is not a header
            names = names or tuple(f"ch{i}" for i in range(width))
            chans = tuple(ChannelSpec(n, "") for n in names)
            self._set_info(DeviceInfo(self.csv_rate_hz, chans, "csv"), events)
        if width != len(self.info.channels):
            self._csv_reject(len(line) + 1)
            return
        host = self._host_next
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


def _csv_kind(line: bytes):
    """Classify a CSV line: ``"skip"`` (blank/comment), ``None`` (unreadable),
    ``("row", width, values)`` or ``("names", width, names)``."""
    try:
        text = line.decode("ascii").strip()
    except UnicodeDecodeError:
        return None
    if not text or text.startswith("#"):
        return "skip"
    fields = [f.strip() for f in text.split(",")] if "," in text else text.split()
    try:
        values = tuple(float(f) for f in fields)
    except ValueError:
        if all(_NAME.match(f) for f in fields) and len(set(fields)) == len(fields):
            return ("names", len(fields), tuple(fields))
        return None
    if not all(abs(v) <= FLOAT32_MAX for v in values):  # NaN, inf and float32 overflow
        return None  # never enter the pipeline (the model reads float32)
    return ("row", len(values), values)


def decode(data: bytes, mode: Mode = "auto", **kw) -> tuple[list[Event], DecoderStats]:
    """Decode a whole byte string at once (for files and tests)."""
    dec = StreamDecoder(mode, **kw)
    return dec.feed(data), dec.stats
