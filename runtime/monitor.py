"""What ``tactile-monitor`` shows of a pen (no model needed): is it alive and sane?

:class:`Watch` turns decoder events into the figures shown: per channel the last value in units
and min/max/RMS over the last second of samples, and the rate received. :func:`block` lays them
out with the link's figures (frames, CRC errors, malformed frames, gaps, samples lost, restarts,
reconnects); :class:`Screen` redraws them in place on a terminal and prints them afresh, plain,
elsewhere. :func:`watch_loop` and :func:`raw_loop` read a
:class:`~tactile.device.link.connection.Connection` (decoded, or the bytes in hex as
:func:`hexdump` shows them); :func:`verdict` is the last line: alive (data at its declared rate
within :data:`RATE_TOLERANCE`, from the first bytes to the end; otherwise ``too slow`` or ``too
fast``) and sane (no channel flat or pinned at its limit, no errors).
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

import tactile.device  # noqa: F401  (registers sim://)
from tactile.device.link import Connection, Reconnected, Stall
from tactile.device.protocol import DeviceInfo, Gap, Header, Samples, StreamDecoder
from tactile.runtime.units import to_units

INT16 = (-32768, 32767)
RATE_TOLERANCE = 0.10  # alive: the rate received within 10% of the declared one
SETTLE_S = 0.5  # the verdict's rate counts from this long after the first samples...
SETTLED_MIN_S = 1.0  # ... when at least this much of the run comes after that


@dataclass
class Watch:
    """Decoder events -> the figures shown. No I/O: tests drive it with events."""

    info: DeviceInfo | None = None
    last: deque = field(default_factory=deque)  # the last second of samples, (C,) in units
    lo: np.ndarray | None = None  # over the whole run, raw counts
    hi: np.ndarray | None = None
    reconnects: int = 0
    stalls: int = 0
    arrivals: deque = field(default_factory=deque)  # (monotonic s, samples so far)
    first_data: float | None = None  # monotonic time of the first bytes
    first_samples: float | None = None  # ... and of the first samples decoded
    # (monotonic s, samples so far) once SETTLE_S have passed since the first samples: what
    # the verdict's rate counts from (a port's backlog, read at once on opening, left out;
    # a CSV board's rows held for its names line come at once too)
    settled: tuple[float, int] | None = None

    def handle(self, events: list) -> None:
        for ev in events:
            if isinstance(ev, Header):
                if self.info is not None and ev.changed:
                    self.last.clear()
                    self.lo = self.hi = None
                self.info = ev.info
            elif isinstance(ev, Samples) and self.info is not None:
                keep = max(1, round(self.info.sample_rate_hz))
                for row in to_units(self.info, ev.raw)[-keep:]:
                    self.last.append(row)
                while len(self.last) > keep:
                    self.last.popleft()
                raw = np.asarray(ev.raw)
                lo, hi = raw.min(axis=0), raw.max(axis=0)
                self.lo = lo if self.lo is None else np.minimum(self.lo, lo)
                self.hi = hi if self.hi is None else np.maximum(self.hi, hi)

    def channel_rows(self) -> list[tuple[str, str, float, float, float, float]]:
        """(name, unit, value, min, max, RMS) per channel over the last second of samples."""
        if self.info is None or not self.last:
            return []
        x = np.array(self.last, np.float64)  # (n, C)
        rms = np.sqrt(np.mean(x * x, axis=0))
        return [(c.name, c.unit, x[-1, k], x[:, k].min(), x[:, k].max(), rms[k])
                for k, c in enumerate(self.info.channels)]

    def rate_hz(self, now: float, samples: int) -> float | None:
        """Samples per second received over the last two seconds (wall time)."""
        self.arrivals.append((now, samples))
        while len(self.arrivals) > 2 and now - self.arrivals[1][0] >= 2.0:
            self.arrivals.popleft()
        t0, s0 = self.arrivals[0]
        return (samples - s0) / (now - t0) if now - t0 >= 0.5 else None

    def problems(self) -> list[str]:
        """What looks wrong about the channels: flat, or pinned at the int16 limit."""
        if self.info is None or self.lo is None or self.info.device == "csv":
            return []
        out = []
        for k, c in enumerate(self.info.channels):
            if self.lo[k] == self.hi[k]:
                out.append(f"{c.name} never changed (stuck at {self.lo[k]} counts)")
            elif self.lo[k] <= INT16[0] or self.hi[k] >= INT16[1]:
                out.append(f"{c.name} reached the int16 limit (saturated)")
        return out


def header_text(info: DeviceInfo, port: str) -> str:
    chans = ", ".join(f"{c.name} [{c.unit}]" if c.unit else c.name for c in info.channels)
    return (f"{info.device} on {port}: protocol {info.protocol_version}, "
            f"{info.sample_rate_hz:g} Hz, {len(info.channels)} channels: {chans}")


def block(watch: Watch, decoder: StreamDecoder, rate: float | None, silent: float | None
          ) -> list[str]:
    """The lines shown each refresh: a heading, one per channel, the link's figures."""
    st = decoder.stats
    rows = watch.channel_rows()
    if rows:
        lines = [f"{'channel':<14}{'value':>11}{'min':>11}{'max':>11}{'RMS':>11}  unit"]
        lines += [f"{n:<14}{v:>11.4g}{lo:>11.4g}{hi:>11.4g}{r:>11.4g}  {u}"
                  for n, u, v, lo, hi, r in rows]
    else:
        lines = [f"waiting for the device's header: {st.bytes_in} bytes, {st.samples} samples"
                 " so far"]
    shown = "-" if rate is None else f"{rate:.1f}"
    quiet = "" if silent is None else f"  no data for {silent:.0f} s"
    lines.append(f"link: frames {st.frames}  samples {st.samples}  crc {st.crc_errors}  "
                 f"malformed {st.malformed}  gaps {st.gaps} (lost {st.samples_lost})  "
                 f"restarts {st.restarts}  reconnects {watch.reconnects}  rate {shown} Hz{quiet}")
    return lines


class Screen:
    """Redraws a block in place on a terminal; prints it afresh, plain, elsewhere."""

    def __init__(self, out=None) -> None:
        self.out = sys.stdout if out is None else out
        self.tty = self.out.isatty()
        self.height = 0  # lines drawn last time (terminal only)
        self.drawing = False

    def show(self, lines: list[str], elapsed: float) -> None:
        self.drawing = True  # (a signal's line written meanwhile leaves the block alone)
        try:
            self._show(lines, elapsed)
        finally:
            self.drawing = False

    def _show(self, lines: list[str], elapsed: float) -> None:
        if self.tty:
            up = f"\x1b[{self.height}F" if self.height else ""
            text = up + "".join(f"\x1b[2K{ln}\n" for ln in lines)
            text += "\x1b[J"  # a shorter block than the last: clear what is left below
            self.height = len(lines)
        else:
            text = f"-- {elapsed:.1f} s\n" + "".join(f"{ln}\n" for ln in lines)
        self.out.write(text)
        self.out.flush()

    def text(self, line: str) -> None:
        """A line above the block (a header), which the next redraw leaves alone."""
        self.out.write(line + "\n")
        self.out.flush()
        self.height = 0

    def clear(self) -> None:
        """On a terminal, erase the block (the next :meth:`show` draws it afresh, below
        whatever is written meanwhile): a line on stderr between two redraws would otherwise
        be drawn over and leave a stale row of the block above the new one."""
        if self.tty and self.height and not self.drawing:
            self.out.write(f"\x1b[{self.height}F\x1b[J")
            self.out.flush()
            self.height = 0


_screen: Screen | None = None  # the block being redrawn (watch_loop's), for say()


def hexdump(offset: int, data: bytes) -> str:
    """``hexdump -C``-style lines: offset, 16 bytes in hex, the printable ones as text."""
    out = []
    for i in range(0, len(data), 16):
        chunk = data[i:i + 16]
        text = "".join(chr(b) if 32 <= b < 127 else "." for b in chunk)
        out.append(f"{offset + i:08x}  {chunk.hex(' '):<47}  |{text}|")
    return "\n".join(out)


def say(msg: str) -> None:
    """A diagnostic line on stderr, as ``tactile-monitor`` writes them (above the block a
    terminal shows: a port lost, a stall, a reconnection stay on the screen)."""
    if _screen is not None and sys.stderr.isatty() and \
            threading.current_thread() is threading.main_thread():  # (the page's server
        _screen.clear()  # thread says things too: it leaves the drawing to the main one)
    print(f"tactile-monitor: {msg}", file=sys.stderr, flush=True)


def raw_loop(conn: Connection) -> int:
    """``--raw``: every byte, in hex, as it arrives, until the connection's stop or deadline;
    returns the number of bytes. (The bytes are decoded too, unseen: a reconnection needs the
    pen's header to know it.)"""
    n = 0
    for chunk in conn.chunks():
        if chunk.data:
            print(hexdump(n, chunk.data), flush=True)
            n += len(chunk.data)
    return n


def watch_loop(conn: Connection, every: float, live=None) -> Watch:
    """Decode until the connection's stop or deadline, show the block every ``every`` s (and at
    the end), feed the live page (a :class:`~tactile.runtime.live.Live`, if given)."""
    global _screen
    watch, decoder, screen = Watch(), conn.decoder, Screen()
    if live is not None:
        live.status = lambda: {**_link_status(decoder), "reconnects": watch.reconnects,
                               "stalls": watch.stalls}
    start = time.monotonic()
    _screen = screen  # say() erases the block before its line
    try:
        _watch(conn, every, live, watch, screen, start)
    finally:
        _screen = None
    watch.handle(conn.decoder.finish())  # rows a CSV board's names line was awaited for
    _show(screen, watch, conn, time.monotonic(), start)  # the last figures
    return watch


def _watch(conn: Connection, every: float, live, watch: Watch, screen: Screen,
           start: float) -> None:
    last_show = start
    for chunk in conn.chunks():
        now = time.monotonic()
        if chunk.data:
            watch.first_data = watch.first_data or now
        if watch.first_samples is None and any(isinstance(ev, Samples) for ev in chunk.events):
            watch.first_samples = now
        if watch.settled is None and watch.first_samples is not None \
                and now - watch.first_samples >= SETTLE_S:
            watch.settled = (now, conn.decoder.stats.samples)  # (this chunk's samples too)
        for ev in chunk.events:
            if isinstance(ev, Header) and (watch.info is None or ev.changed):
                screen.text(header_text(ev.info, conn.port))
            elif isinstance(ev, Reconnected):
                watch.reconnects += 1
            elif isinstance(ev, Stall):
                watch.stalls += 1
            if live is not None:
                _publish(live, ev)
        watch.handle(chunk.events)
        if now - last_show >= every:
            last_show = now
            _show(screen, watch, conn, now, start)


def _show(screen: Screen, watch: Watch, conn: Connection, now: float, start: float) -> None:
    rate = watch.rate_hz(now, conn.decoder.stats.samples)
    screen.show(block(watch, conn.decoder, rate, conn.silent_for(now)), now - start)


def _publish(live, ev) -> None:
    """A decoder or link event to the live page, as ``tactile-run`` gives it."""
    if isinstance(ev, Gap):
        live.feed({"event": "gap", "seq": ev.seq, "missing": ev.missing, "reason": ev.reason})
    elif isinstance(ev, Stall):
        live.feed({"event": "stall", "seconds": ev.seconds})
    elif isinstance(ev, Reconnected):
        live.feed({"event": "reconnect", "port": ev.port, "offline_s": ev.offline_s})
    else:
        live.feed(ev)


def _link_status(decoder: StreamDecoder) -> dict:
    from tactile.runtime.live import link_status

    return link_status(decoder.stats)


def verdict(watch: Watch, decoder: StreamDecoder, end: float) -> str:
    """One line: alive (the rate received, within :data:`RATE_TOLERANCE` of the declared one;
    else ``too slow`` or ``too fast``) and sane (no errors, gaps, flat or saturated channels;
    else each is named). The rate counts from :data:`SETTLE_S` after the first samples to
    ``end`` (monotonic s), when that leaves at least :data:`SETTLED_MIN_S`: what waited in the
    port comes at once when it opens (and a CSV board's rows held for its names line), and
    made a pen at its rate ``too fast``; a shorter run counts from the first bytes."""
    st = decoder.stats
    declared = watch.info.sample_rate_hz if watch.info else math.nan
    seconds = end - watch.first_data if watch.first_data is not None else 0.0
    got = st.samples / seconds if seconds > 0 else math.inf
    over = ""
    if watch.settled is not None and end - watch.settled[0] >= SETTLED_MIN_S:
        got = (st.samples - watch.settled[1]) / (end - watch.settled[0])
        over = f" over the last {end - watch.settled[0]:.1f} s"
    notes = watch.problems()
    if st.errors:  # each kind there is, by name
        kinds = ((st.crc_errors, "CRC error", "CRC errors"),
                 (st.malformed, "malformed frame", "malformed frames"),
                 (st.csv_rejected, "CSV line not read", "CSV lines not read"),
                 (st.unsupported, "header of an unsupported protocol",
                  "headers of an unsupported protocol"))
        notes.append(", ".join(f"{n} {one if n == 1 else many}" for n, one, many in kinds if n)
                     + (" (a port opened mid-line cuts one)" if st.csv_rejected else ""))
    if st.gaps:
        notes.append(f"{st.gaps} gap{'' if st.gaps == 1 else 's'} ({st.samples_lost} samples "
                     "lost)")
    off = abs(got / declared - 1) if declared > 0 else math.inf
    if off <= RATE_TOLERANCE:
        head = "alive" + ("" if notes else " and sane")
        rate = f"{got:.1f} Hz received{over}, {declared:g} Hz declared"
    else:
        head = ("too slow" if got < declared else "too fast") + ("" if notes else
                                                                 ", otherwise sane")
        rate = (f"{got:.1f} Hz received{over}, {declared:g} Hz declared: more than "
                f"{RATE_TOLERANCE:.0%} off")
    return (f"{head}: {st.samples} samples in {seconds:.1f} s ({rate})"
            + ("; " + "; ".join(notes) if notes else ""))
