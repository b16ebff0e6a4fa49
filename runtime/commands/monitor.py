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
says whether the pen was alive (data at its declared rate within 10%,
:data:`~tactile.runtime.monitor.RATE_TOLERANCE`, from the first bytes to the end; otherwise ``too
slow`` or ``too fast``) and sane (no channel flat or pinned at its limit, no errors). Exit codes:
0 data came (whatever the verdict), or Ctrl-C or SIGTERM stopped it before the port sent any
byte; 1 bad arguments; 2 the port cannot be opened, or bytes but no decodable samples came, or
nothing came by ``--seconds``; 4 stdout cannot be written (a full disk).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING

from tactile.cli import (
    Parser,
    add_debug,
    add_port_options,
    command,
    float_in,
    link_values,
    run,
)

if TYPE_CHECKING:
    from tactile.device.protocol import StreamDecoder

CSV_RATE = 100.0  # --csv-rate's default, Hz


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="tactile-monitor",
        description="Show a pen's header and live values (no model needed): per channel the "
        "last value in units and min/max/RMS over the last second, and the link's figures.",
        epilog="exit codes: 0 data came, or Ctrl-C/SIGTERM before any byte; 1 bad arguments; "
        "2 port cannot be opened, no pen found, or no samples came; 4 stdout cannot be written "
        "(a full disk)",
    )
    p.add_argument("--port", help="device path or pyserial URL (sim://, socket://, ...); "
                   "default: the one likely pen attached (tactile-ports lists them)")
    p.add_argument("--raw", action="store_true",
                   help="show the bytes as they arrive, in hex (as hexdump -C), not decoded")
    p.add_argument("--every", type=float_in(0.0), default=None,
                   help="refresh period, s (default 0.5 in a terminal, 1 otherwise)")
    p.add_argument("--csv-rate", type=float_in(0.0),
                   help=f"rate of a CSV-line device, Hz (it declares none; default {CSV_RATE:g})")
    add_port_options(p, "the channels and link", until="Ctrl-C")
    add_debug(p)
    return p


def _monitor(args: argparse.Namespace) -> int:
    from tactile.device.link.connection import Connection, LinkSettings
    from tactile.device.link.portlist import find_port
    from tactile.device.protocol import StreamDecoder
    from tactile.errors import ConfigError, DeviceError
    from tactile.runtime.monitor import raw_loop, say, verdict, watch_loop
    from tactile.runtime.stop import stop_on_signals

    every = args.every if args.every is not None else 0.5 if sys.stdout.isatty() else 1.0
    if args.raw:  # the bytes as they come: nothing decoded, nothing redrawn
        given = next((f"--{k.replace('_', '-')}" for k in ("serve", "every", "csv_rate")
                      if getattr(args, k) is not None), None)
        if given is not None:
            raise ConfigError(f"--raw shows the bytes as they arrive; {given} is for decoded "
                              "samples: give one")
    stop = stop_on_signals(say)
    if stop is None:  # a signal while starting
        return 0
    auto = args.port is None  # found by auto-detection: after an unplug, look again
    port = args.port if args.port is not None else find_port()
    live = None
    if args.serve:
        from tactile.runtime.live import Live, parse_address

        live = Live(*parse_address(args.serve), status=dict, say=say, labels=False)
    begin = time.monotonic()
    baud, stall_timeout = link_values(args)
    settings = LinkSettings(port, baud, auto=auto, stall_timeout=stall_timeout)
    decoder = StreamDecoder(csv_rate_hz=CSV_RATE if args.csv_rate is None else args.csv_rate)
    try:
        with Connection(settings, decoder, stop, say, begin + args.seconds) as conn:
            conn.open()
            if args.raw:
                if raw_loop(conn) == 0:
                    if stop.get("by"):  # stopped before the port said anything
                        say(f"stopped by {stop['by']} before any data")
                        return 0
                    raise DeviceError(f"no data from {port} in {time.monotonic() - begin:.1f} s")
                return 0
            watch = watch_loop(conn, every, live)
            end = time.monotonic()  # before closing the page, which may wait for its viewers
    finally:
        if live is not None:
            live.close()
    if decoder.stats.samples == 0:
        st = decoder.stats
        if stop.get("by") and not st.bytes_in:  # a silent port, stopped: as tactile-record
            say(f"stopped by {stop['by']} before any data")
            return 0
        raise DeviceError(no_samples(port, end - begin, decoder))
    say(verdict(watch, decoder, end))
    return 0


def no_samples(port: str, seconds: float, decoder: StreamDecoder) -> str:
    """The error for a port that gave no sample: the bytes read, and how many of them decoded
    to nothing: those thrown away and those still held waiting for a frame's or a line's end
    (a wrong device or baud rate can send bytes that never end a frame)."""
    st = decoder.stats
    return (f"no samples from {port} in {seconds:.1f} s ({st.bytes_in} bytes read; "
            f"{st.bytes_discarded + decoder.held} not decodable)")


@command("tactile-monitor", guarded=True)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run("tactile-monitor", _monitor, args)


if __name__ == "__main__":
    sys.exit(main())
