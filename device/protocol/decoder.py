"""The stream decoder: bytes in, samples and events out.

A pure state machine with no I/O (pyserial's ``Packetizer`` idea): call :meth:`StreamDecoder.feed`
with whatever bytes arrived and get back a list of events in stream order. It

* recognises binary frames (``device/PROTOCOL.md``) or CSV lines automatically;
* never raises on bad bytes: garbage, CRC failures and malformed frames are skipped and counted;
* resynchronises within one frame: a frame whose leading delimiter was lost, or that has garbage
  glued in front of it, is still recovered (see :func:`tactile.device.protocol.codec.find_frame`);
* costs O(n) for n bytes whatever they are, split into reads of any size;
* never invents or reorders samples: duplicates are dropped, overlaps trimmed, gaps reported with
  their size, and a device restart is reported as a gap;
* refuses a header of a protocol version it does not read, and the samples that follow it;
* keeps a bounded buffer (at most one maximal frame plus one read).

The rules are those of ``device/PROTOCOL.md`` ("What a receiver does").
"""

from __future__ import annotations

import math
from collections import deque
from typing import Literal

import numpy as np

from tactile.contract_keys import MAX_RATE_HZ
from tactile.device.protocol.codec import (
    MAX_ENCODED,
    MIN_ENCODED,
    SEQ_MODULO,
    SUPPORTED_VERSIONS,
    HeaderFrame,
    SamplesFrame,
    find_frame,
)
from tactile.device.protocol.csv_lines import _RESTART, MAX_CSV_LINE, CsvLines, csv_kind
from tactile.device.protocol.events import DecoderStats, Event, Gap, Header, Samples
from tactile.device.protocol.info import DeviceInfo
from tactile.errors import ConfigError

AUTO_PENDING = 8192  # bytes held while the decoder is still deciding binary vs CSV
REPLAY_WINDOW = 4096  # delivered samples remembered to recognise a re-sent frame
_HALF = SEQ_MODULO // 2
_MIN_PERIOD_US, _MAX_PERIOD_US = 1, 1_000_000  # sample rates from 1 MHz down to 1 Hz

Mode = Literal["auto", "binary", "csv"]


class StreamDecoder(CsvLines):
    """Incremental decoder for one device stream (its CSV line mode: :class:`CsvLines`).

    Args:
        mode: ``"auto"`` (default: decide from the bytes), ``"binary"`` or ``"csv"``.
        csv_rate_hz: sample rate assumed for CSV streams (they carry none), in (0, 1e6].
        replay_window: how many delivered samples are remembered to recognise a re-sent frame
            by its contents (a frame going back that matches them is a duplicate, one that
            contradicts them means the device restarted).
        line_start: the first byte fed begins a line (a file). A port opened on a running
            device begins anywhere, so by default a first CSV line that is a row is not taken
            as data: its first number may be cut (a names line is taken).
    """

    def __init__(
        self, mode: Mode = "auto", csv_rate_hz: float = 100.0,
        replay_window: int = REPLAY_WINDOW, line_start: bool = False,
    ) -> None:
        if mode not in ("auto", "binary", "csv"):
            raise ConfigError(f"decoder mode {mode!r}: must be one of auto, binary, csv")
        if not (math.isfinite(csv_rate_hz) and 0 < csv_rate_hz <= MAX_RATE_HZ):
            raise ConfigError(f"csv rate {csv_rate_hz!r} Hz: must be a number in "
                              f"(0, {MAX_RATE_HZ:g}]")
        self.mode: Mode = mode
        self.csv_rate_hz = float(csv_rate_hz)
        self.replay_window = int(replay_window)
        self.stats = DecoderStats()
        self.info: DeviceInfo | None = None
        self._buf = bytearray()
        self._scan = 0  # bytes of _buf already searched for a delimiter
        self._line_partial = not line_start  # the first line in _buf may be cut: not data
        # auto mode: how far the held bytes were examined
        self._det_chunk = 0
        self._det_line = 0
        self._det_prev: int | None = None  # width of the previous readable CSV line
        # binary sequence state: next expected device seq (u32 and unwrapped), host seq
        self._dev_next: int | None = None
        self._dev_next_u = 0
        self._session_first_u = 0  # unwrapped device seq of the first frame since a restart
        self._host_next = 0
        self._t_last: int | None = None  # device time of the last delivered frame, u32
        self._t_host = 0  # unwrapped device time of the last delivered frame
        self._restart_pending = False  # set by reconnected()
        self._header_since_samples = False
        self._history: deque[tuple[int, int, np.ndarray]] = deque()  # (seq_u, t_us, raw)
        self._history_n = 0
        self._frame_width: int | None = None  # before any header: the first frame's width
        self._refusing = False  # the last header was of a version we do not read
        # csv state
        self._csv_width: int | None = None
        self._csv_held: list = []  # (kind, nbytes) while the width is undecided
        self._mid_run = not line_start  # a port opened on a running board: names may follow
        self._csv_wait: list | None = None  # (kind, nbytes) of rows waiting for a names line
        self._csv_wait_bytes = 0  # ... and their bytes
        self._csv_run = (0, 0)  # (width, readable lines of that width in a row)
        self._csv_names: tuple[str, ...] | None = None
        self._csv_rejected_run = 0

    # -- public ------------------------------------------------------------------------------------

    def feed(self, data: bytes) -> list[Event]:
        """Consume ``data`` (any length, any split) and return the events it completes.

        Never raises on any bytes: what cannot be used is counted in :attr:`stats`."""
        self.stats.bytes_in += len(data)
        buf = self._buf
        # No delimiter of the mode in the read and nothing to cut: all the full path would do is
        # append, and remember where the search for a delimiter stopped (small reads, kept cheap;
        # `0 in data` tests for a zero byte several times faster than `b"\x00" in data`)
        mode = self.mode
        if mode == "binary":
            if 0 not in data and len(buf) + len(data) <= MAX_ENCODED:
                buf += data
                self._scan = len(buf)
                return []
        elif mode == "csv":
            if 10 not in data and len(buf) + len(data) <= MAX_CSV_LINE:
                buf += data
                self._scan = len(buf)
                return []
        elif (0 not in data and 10 not in data
              and len(buf) + len(data) <= AUTO_PENDING):
            buf += data  # _detect looks at completed chunks and lines only
            return []
        buf += data
        if self.mode == "auto":
            mode = self._detect()
            if mode == "auto":
                if len(self._buf) > AUTO_PENDING:  # bounded: forget the oldest half
                    self._forget(len(self._buf) - AUTO_PENDING // 2)
                return []
            self.mode = mode
            self._scan = 0
        if self.mode == "binary":
            return self._feed_binary()
        return self._feed_csv()

    def reconnected(self) -> None:
        """The link was re-opened: drop partial bytes and expect the device to have restarted.

        The next samples frame is then reported after a ``restart`` gap whatever its sequence
        number, since a pen that was unplugged rebooted and counts from 0 again; so is a CSV
        board's next row (the lines carry no count: the break is known from the link alone).
        """
        self.stats.bytes_discarded += len(self._buf)
        self._buf.clear()
        self._scan = self._det_chunk = self._det_line = 0
        self._line_partial = True
        if self._dev_next is not None:
            self._dev_next = None
            self._restart_pending = True
        elif self._csv_width is not None and self.info is not None:  # a CSV board: no count
            self._restart_pending = True  # to tell, so its next row comes after the break
        elif self._csv_wait is not None:  # rows waiting for names: the break goes among them
            self._csv_wait.append((_RESTART, 0))

    @property
    def held(self) -> int:
        """Bytes received and neither decoded nor discarded yet: the start of a frame or line
        whose end has not come (or, in auto mode, bytes not yet seen to be either)."""
        return len(self._buf)

    @property
    def next_seq(self) -> int:
        """Host sequence number the next sample will get (if nothing is lost)."""
        return self._host_next

    # -- detection ---------------------------------------------------------------------------------

    def _detect(self) -> Mode:
        """Look at what arrived since the last call (each byte once): a frame that passes the
        CRC means binary; two readable CSV lines of the same width in a row mean CSV."""
        buf = self._buf
        start = self._det_chunk
        while (end := buf.find(b"\x00", start)) >= 0:
            chunk = bytes(buf[max(start, end - MAX_ENCODED) : end])
            start = end + 1
            if len(chunk) >= MIN_ENCODED and find_frame(chunk)[0] is not None:
                return "binary"
        self._det_chunk = start
        start = self._det_line
        while (end := buf.find(b"\n", start)) >= 0:
            line = bytes(buf[start:end])
            first = start == 0 and self._line_partial
            start = end + 1
            kind = csv_kind(line) if len(line) <= MAX_CSV_LINE else None
            if kind == "skip" or (first and kind is not None and kind[0] == "row"):
                continue  # a row that may be cut is no evidence
            if kind is not None and kind[0] == "row" and self._det_prev == kind[1]:
                return "csv"
            self._det_prev = None if kind is None else kind[1]
        self._det_line = start
        return "auto"

    def _forget(self, cut: int) -> None:
        """Drop the oldest ``cut`` held bytes (auto mode, undecided), counted as discarded."""
        nl = self._buf.find(b"\n", cut)
        if 0 <= nl < len(self._buf) - 1:  # keep whole lines where there is a line end
            cut = nl + 1
            self._line_partial = False
        else:
            self._line_partial = True
        self.stats.bytes_discarded += cut
        del self._buf[:cut]
        self._det_chunk = max(0, self._det_chunk - cut)
        self._det_line = max(0, self._det_line - cut)

    # -- binary ------------------------------------------------------------------------------------

    def _width(self) -> int | None:
        return len(self.info.channels) if self.info is not None else self._frame_width

    def _feed_binary(self) -> list[Event]:
        events: list[Event] = []
        buf = self._buf
        start = 0
        while (end := buf.find(b"\x00", max(start, self._scan))) >= 0:
            chunk = bytes(buf[start:end])
            start = end + 1
            if not chunk:
                continue
            if len(chunk) > MAX_ENCODED:  # only the tail can hold a frame
                self.stats.bytes_discarded += len(chunk) - MAX_ENCODED
                self.stats.malformed += 1
                chunk = chunk[-MAX_ENCODED:]
            parsed, skipped, failure = find_frame(chunk, self._width())
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
        self._scan = len(buf)
        return events

    def _on_frame(self, parsed: SamplesFrame | HeaderFrame, events: list[Event]) -> None:
        self.stats.frames += 1
        if isinstance(parsed, HeaderFrame):
            self.stats.header_frames += 1
            self._on_header(parsed.info, events)
            return
        if self._refusing:  # its device's header was refused: not data we can honour
            self.stats.refused += 1
            return
        width = self._width()
        if width is None:  # before any header, the first frame fixes the width
            self._frame_width = width = parsed.raw.shape[1]
        if parsed.raw.shape[1] != width:
            # CRC-valid but contradicts the header: trust neither, drop it visibly
            self.stats.frames -= 1
            self.stats.malformed += 1
        else:
            self._accept(parsed, events)

    def _on_header(self, info: DeviceInfo, events: list[Event]) -> None:
        self._header_since_samples = True
        if info.protocol_version not in SUPPORTED_VERSIONS:
            self.stats.unsupported += 1
            if not self._refusing:
                self._refusing = True
                self.stats.gaps += 1
                versions = ", ".join(str(v) for v in sorted(SUPPORTED_VERSIONS))
                events.append(Gap(self._host_next, 0, "unsupported",
                                  f"device header of protocol version {info.protocol_version}; "
                                  f"this decoder reads {versions}: its samples are dropped"))
            return
        self._refusing = False
        self._set_info(info, events)

    def _accept(self, parsed: SamplesFrame, events: list[Event]) -> None:
        """Place a samples frame of the right width in the sequence: in order, after a drop,
        a duplicate or late frame (dropped), a partial re-send (its new tail kept), or the
        first frame of a restarted device."""
        raw = parsed.raw
        n = raw.shape[0]
        t = parsed.t_us
        if self._restart_pending:  # first frame after a reconnection
            self._restart_pending = False
            self._restart(parsed.seq, events)
            host, s_u = self._host_next, parsed.seq
        elif self._dev_next is None:  # first frame: host seq starts at the device's count
            host = s_u = parsed.seq
            self._session_first_u = s_u
            self._t_host = t
            self._t_last = t
        else:
            diff = (parsed.seq - self._dev_next) % SEQ_MODULO
            if diff < _HALF and self._restarted(diff, t):
                self._restart(parsed.seq, events)
                host, s_u = self._host_next, parsed.seq
            elif diff < _HALF:  # forward: in order, or a drop of `diff` samples
                host = self._host_next + diff
                s_u = self._dev_next_u + diff
                if diff:
                    self.stats.gaps += 1
                    self.stats.samples_lost += diff
                    events.append(Gap(host, diff, "drop"))
            else:
                s_u = self._dev_next_u - (SEQ_MODULO - diff)
                verdict = self._behind(s_u, t, raw)
                if verdict == "duplicate":
                    self.stats.duplicates += 1
                    return
                if verdict == "late":
                    self.stats.late += 1
                    return
                if verdict == "tail":  # a re-send split differently: keep only what is new
                    k = self._dev_next_u - s_u
                    raw = raw[k:]
                    n = raw.shape[0]
                    t = (t + round(k * self._period_us())) % SEQ_MODULO
                    s_u = self._dev_next_u
                    host = self._host_next
                else:  # the device restarted
                    self._restart(parsed.seq, events)
                    host, s_u = self._host_next, parsed.seq
        self._t_host += self._dt(t)
        self._t_last = t
        self._dev_next_u = s_u + n
        self._dev_next = self._dev_next_u % SEQ_MODULO
        self._host_next = host + n
        self._header_since_samples = False
        self._remember(s_u, t, raw)
        self.stats.samples += n
        events.append(Samples(host, self._t_host, raw))

    def _behind(self, s_u: int, t: int, raw: np.ndarray) -> str:
        """A frame whose sequence number went back: ``"duplicate"``, ``"tail"`` (it also holds
        new samples), ``"late"`` or ``"restart"``.

        A re-sent frame repeats samples we delivered, with their contents and device times; a
        device that restarted counts again with other contents. A frame that went back but
        holds none of the samples remembered is late (its samples were reported lost) when it
        is recent (within ``replay_window``), either within the span remembered, or with no
        header since the last frame (a device sends its header when it starts), or with a count
        no device that started within ``replay_window`` samples has, and its device
        time fits (by the rate when one is known, else it is earlier by what a rate between
        1 Hz and 1 MHz explains); else the device restarted. So a frame behind its whole run
        with a fresh count after a header is a restart even when its time fits: those are the
        bytes of a device that restarted again (``device/PROTOCOL.md``, "Restart"), and
        reading them as late would join its next frames to the run before it."""
        end = min(s_u + len(raw), self._dev_next_u)
        period = self._period_us(estimate_only=True)
        matched = 0
        for hs, ht, hraw in self._history:
            lo, hi = max(hs, s_u), min(hs + len(hraw), end)
            if lo >= hi:
                continue
            if not np.array_equal(hraw[lo - hs : hi - hs], raw[lo - s_u : hi - s_u]):
                return "restart"
            if period is None:  # times comparable only for the same first sample
                if hs == s_u and ht != t:
                    return "restart"
            else:
                skew = (t - ht + round((hs - s_u) * period) + _HALF) % SEQ_MODULO - _HALF
                if abs(skew) > max(period / 2, 1):
                    return "restart"
            matched += hi - lo
        if matched:
            return "tail" if s_u + len(raw) > self._dev_next_u else "duplicate"
        oldest = self._history[0][0] if self._history else self._dev_next_u
        recent = s_u >= self._dev_next_u - self.replay_window
        # a header since the last frame may be a restarted device's, but only a device that
        # started within the last `replay_window` samples counts that low
        fresh = s_u % SEQ_MODULO < self.replay_window
        if recent and (s_u >= oldest or not self._header_since_samples or not fresh):
            if self._history:  # and its device time fits this run of the device
                hs, ht, _ = self._history[-1]
                if period is not None:
                    skew = (t - ht + round((hs - s_u) * period) + _HALF) % SEQ_MODULO - _HALF
                    if abs(skew) > max(2 * period, 1000):
                        return "restart"
                elif not (hs - s_u) * _MIN_PERIOD_US <= (ht - t) % SEQ_MODULO \
                        <= (hs - s_u) * _MAX_PERIOD_US:  # earlier by what some rate explains
                    return "restart"
            return "late"
        return "restart"

    def _restarted(self, ahead: int, t: int) -> bool:
        """A frame ``ahead`` samples past the next expected one whose device time says
        otherwise (by the period the remembered frames show, else the header's rate, else
        ``csv_rate_hz`` for a jump): the device restarted and its count happens to be where
        the old one was, or ahead (its header, which says so, may have been lost)."""
        if self._t_last is None:
            return False
        period = self._period_us(estimate_only=True)
        if period is None:
            if not ahead:  # no rate known: a clock that moved by more than 1 s per sample
                steps = len(self._history[-1][2]) if self._history else 1
                return (t - self._t_last) % SEQ_MODULO > steps * _MAX_PERIOD_US
            period = self._period_us()
        last_n = len(self._history[-1][2]) if self._history else 1
        expect = round((ahead + last_n) * period)
        skew = ((t - self._t_last) - expect + _HALF) % SEQ_MODULO - _HALF
        return abs(skew) > max(2 * period, 1000)

    def _remember(self, s_u: int, t: int, raw: np.ndarray) -> None:
        self._history.append((s_u, t, raw))
        self._history_n += len(raw)
        while self._history and self._history_n - len(self._history[0][2]) >= self.replay_window:
            self._history_n -= len(self._history.popleft()[2])

    def _restart(self, seq: int, events: list[Event]) -> None:
        """The device restarted: continue the host count, mark the break, forget its clock."""
        self.stats.restarts += 1
        self.stats.gaps += 1
        events.append(Gap(self._host_next, 0, "restart"))
        self._t_last = None
        self._history.clear()
        self._history_n = 0
        self._session_first_u = seq

    def _period_us(self, estimate_only: bool = False) -> float | None:
        """Device microseconds per sample: as the device's own clock shows it in the frames
        remembered (a board's clock may not match the rate its header declares), else from the
        header's rate, else (unless ``estimate_only``) from ``csv_rate_hz``."""
        if len(self._history) >= 2:
            (s0, t0, _), (s1, t1, _) = self._history[0], self._history[-1]
            if s1 > s0:
                return ((t1 - t0) % SEQ_MODULO) / (s1 - s0)
        if self.info is not None:
            return 1e6 / self.info.sample_rate_hz
        return None if estimate_only else 1e6 / self.csv_rate_hz

    def _dt(self, t_us: int) -> int:
        if self._t_last is None:  # restart: no relation to the old clock; advance one period
            return round(self._period_us())
        return (t_us - self._t_last) % SEQ_MODULO

    def _set_info(self, info: DeviceInfo, events: list[Event]) -> None:
        if self.info is None:
            self.info = info
            events.append(Header(info, changed=False))
        elif info != self.info:
            self.stats.header_changes += 1
            self.info = info
            events.append(Header(info, changed=True))


def decode(data: bytes, mode: Mode = "auto", **kw) -> tuple[list[Event], DecoderStats]:
    """Decode a whole byte string at once (for files and tests: it begins at a line start
    unless ``line_start=False``)."""
    kw.setdefault("line_start", True)
    dec = StreamDecoder(mode, **kw)
    return dec.feed(data), dec.stats
