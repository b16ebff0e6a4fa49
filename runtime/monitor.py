"""``tactile-monitor``: is my pen alive and sane? Live values, no model needed.

    tactile-monitor                                   # the one likely pen attached
    tactile-monitor --port /dev/ttyACM0 --seconds 5   # a table refreshed in place, then a verdict
    tactile-monitor --port /dev/ttyACM0 --raw         # the bytes, in hex, as they arrive
    tactile-monitor --port /dev/ttyACM0 --serve 0.0.0.0:8000   # and a live page for a phone

It prints the pen's header (device, rate, channels with units), then one line per channel (the
last value in units, min/max/RMS over the last second of samples) and a line of link figures
(frames, CRC errors, malformed frames, gaps, samples lost, restarts, reconnects, the rate
actually received). In a terminal the block is redrawn in place; otherwise (a pipe, a log file)
it is printed again every ``--every`` seconds, with no escape codes. At the end a line on stderr
says whether the pen was alive (data at its declared rate within :data:`RATE_TOLERANCE`, from the
first bytes to the end; otherwise ``too slow`` or ``too fast``) and sane (no channel flat or
pinned at its limit, no errors). Exit codes: 0 data came (whatever the verdict), 1 bad arguments,
2 the port cannot be opened, or no data (no decodable samples) came.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

import tactile.device  # noqa: F401  (registers sim://)
from tactile.cli import Parser, add_debug, add_port_options, float_in, run, started
from tactile.device.link import Connection, LinkSettings, Reconnected, Stall, find_port
from tactile.device.protocol import DeviceInfo, Gap, Header, Samples, StreamDecoder
from tactile.errors import ConfigError, DeviceError
from tactile.runtime.units import to_units

INT16 = (-32768, 32767)
RATE_TOLERANCE = 0.10  # alive: the rate received within 10% of the declared one


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

    def show(self, lines: list[str], elapsed: float) -> None:
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


def hexdump(offset: int, data: bytes) -> str:
    """``hexdump -C``-style lines: offset, 16 bytes in hex, the printable ones as text."""
    out = []
    for i in range(0, len(data), 16):
        chunk = data[i:i + 16]
        text = "".join(chr(b) if 32 <= b < 127 else "." for b in chunk)
        out.append(f"{offset + i:08x}  {chunk.hex(' '):<47}  |{text}|")
    return "\n".join(out)


def _say(msg: str) -> None:
    print(f"tactile-monitor: {msg}", file=sys.stderr, flush=True)


def raw_loop(conn: Connection, stop: dict, deadline: float) -> int:
    """``--raw``: every byte, in hex, as it arrives; returns the number of bytes. (The bytes
    are decoded too, unseen: a reconnection needs the pen's header to know it.)"""
    n = 0
    while not stop["flag"] and time.monotonic() < deadline:
        chunk = conn.read()
        if chunk is None:
            break
        if chunk.data:
            print(hexdump(n, chunk.data), flush=True)
            n += len(chunk.data)
    return n


def watch_loop(args: argparse.Namespace, conn: Connection, stop: dict, deadline: float, live
               ) -> Watch:
    """Decode, show the block every ``--every`` s (and at the end), feed the live page."""
    watch, decoder, screen = Watch(), conn.decoder, Screen()
    if live is not None:
        live.status = lambda: {**_link_status(decoder), "reconnects": watch.reconnects,
                               "stalls": watch.stalls}
    start = last_show = time.monotonic()
    while True:
        done = stop["flag"] or time.monotonic() >= deadline
        chunk = None if done else conn.read()
        now = time.monotonic()
        if chunk is not None and chunk.data:
            watch.first_data = watch.first_data or now
        for ev in chunk.events if chunk is not None else ():
            if isinstance(ev, Header) and (watch.info is None or ev.changed):
                screen.text(header_text(ev.info, conn.port))
            elif isinstance(ev, Reconnected):
                watch.reconnects += 1
            elif isinstance(ev, Stall):
                watch.stalls += 1
            if live is not None:
                _publish(live, ev)
        if chunk is not None:
            watch.handle(chunk.events)
        if chunk is None or now - last_show >= args.every:
            last_show = now
            rate = watch.rate_hz(now, decoder.stats.samples)
            screen.show(block(watch, decoder, rate, conn.silent_for(now)), now - start)
        if chunk is None:
            return watch


def _publish(live, ev) -> None:
    """A decoder or link event to the live page, as ``tactile-run`` gives it."""
    if isinstance(ev, Gap):
        live.feed({"event": "gap", "seq": ev.seq, "missing": ev.missing, "reason": ev.reason})
    elif isinstance(ev, Stall):
        live.feed({"event": "stall", "seconds": ev.seconds})
    elif isinstance(ev, Reconnected):
        live.feed({"event": "reconnect", "port": ev.port})
    else:
        live.feed(ev)


def _link_status(decoder: StreamDecoder) -> dict:
    from tactile.runtime.serve import link_status

    return link_status(decoder.stats)


def verdict(watch: Watch, decoder: StreamDecoder, end: float) -> str:
    """One line: alive (the rate received from the first bytes to ``end``, monotonic s, within
    :data:`RATE_TOLERANCE` of the declared one; else ``too slow`` or ``too fast``) and sane
    (no errors, gaps, flat or saturated channels; else each is named)."""
    st = decoder.stats
    declared = watch.info.sample_rate_hz if watch.info else math.nan
    seconds = end - watch.first_data if watch.first_data is not None else 0.0
    got = st.samples / seconds if seconds > 0 else math.inf
    notes = watch.problems()
    if st.errors:
        notes.append(f"{st.crc_errors} CRC errors, {st.malformed} malformed frames")
    if st.gaps:
        notes.append(f"{st.gaps} gaps ({st.samples_lost} samples lost)")
    off = abs(got / declared - 1) if declared > 0 else math.inf
    if off <= RATE_TOLERANCE:
        head = "alive" + ("" if notes else " and sane")
        rate = f"{got:.1f} Hz received, {declared:g} Hz declared"
    else:
        head = ("too slow" if got < declared else "too fast") + ("" if notes else
                                                                 ", otherwise sane")
        rate = (f"{got:.1f} Hz received, {declared:g} Hz declared: more than "
                f"{RATE_TOLERANCE:.0%} off")
    return (f"{head}: {st.samples} samples in {seconds:.1f} s ({rate})"
            + ("; " + "; ".join(notes) if notes else ""))


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="tactile-monitor",
        description="Show a pen's header and live values (no model needed): per channel the "
        "last value in units and min/max/RMS over the last second, and the link's figures.",
        epilog="exit codes: 0 data came, 1 bad arguments, 2 port cannot be opened, no pen "
        "found, or no data came",
    )
    p.add_argument("--port", help="device path or pyserial URL (sim://, socket://, ...); "
                   "default: the one likely pen attached (tactile-ports lists them)")
    p.add_argument("--raw", action="store_true",
                   help="show the bytes as they arrive, in hex (as hexdump -C), not decoded")
    p.add_argument("--every", type=float_in(0.0), default=None,
                   help="refresh period, s (default 0.5 in a terminal, 1 otherwise)")
    p.add_argument("--csv-rate", type=float_in(0.0), default=100.0,
                   help="rate of a CSV-line device, Hz (it declares none)")
    add_port_options(p, "the channels and link")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    if args.every is None:
        args.every = 0.5 if sys.stdout.isatty() else 1.0
    if args.raw and args.serve:
        raise ConfigError("--raw shows the bytes only, --serve needs decoded samples: give one")
    stop = {"flag": False}
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *_: stop.__setitem__("flag", True))
    early = started()  # after our handlers are in place: no signal falls between the two
    if early:
        _say(f"stopped by {early} while starting")
        return 0
    auto = args.port is None  # found by auto-detection: after an unplug, look again
    port = args.port = args.port or find_port()
    live = None
    if args.serve:
        from tactile.runtime.serve import Live, parse_address

        live = Live(*parse_address(args.serve), status=dict, say=_say, labels=False)
    begin = time.monotonic()
    deadline = begin + args.seconds
    settings = LinkSettings(port, args.baud, auto=auto, stall_timeout=args.stall_timeout)
    decoder = StreamDecoder(csv_rate_hz=args.csv_rate)
    try:
        with Connection(settings, decoder, stop, _say, deadline) as conn:
            conn.open()
            if args.raw:
                if raw_loop(conn, stop, deadline) == 0:
                    raise DeviceError(f"no data from {port} in {time.monotonic() - begin:.1f} s")
                return 0
            watch = watch_loop(args, conn, stop, deadline, live)
            end = time.monotonic()  # before closing the page, which may wait for its viewers
    finally:
        if live is not None:
            live.close()
    took = end - begin
    if decoder.stats.samples == 0:
        st = decoder.stats
        raise DeviceError(f"no samples from {port} in {took:.1f} s ({st.bytes_in} bytes read; "
                          f"{st.bytes_discarded} not decodable)")
    _say(verdict(watch, decoder, end))
    return 0


def main(argv: list[str] | None = None) -> int:
    return run("tactile-monitor", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
