"""``tactile-record``: read a pen and write labelled takes.

    tactile-record --port sim://?texture=paper --label paper --seconds 60 --out data/

Data (the paths of the takes written) goes to stdout, progress and diagnostics to stderr. Ctrl-C
or SIGTERM finishes the take cleanly; a killed recorder leaves a readable take holding every
sample that had reached it after the pen's header, and every gap among them. A vanished port is
reopened with backoff and the take goes on after a ``restart`` gap. A header change (another
pen, another layout) starts a new take.
"""

from __future__ import annotations

import argparse
import math
import re
import sys

from tactile.cli import BAUD, Parser, add_debug, command, float_in, int_in, path_given, run


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="tactile-record",
        description="Record labelled takes from a pen (device path or pyserial URL).",
        epilog="Ctrl-C or SIGTERM finishes the take (written and closed) and exits 0; stopped "
               "before the port gave any data, it exits 0 and says so. Exit 2: the port cannot "
               "be opened, or it gave no usable data before the end. Exit 1: a take cannot be "
               "written (a full disk: the line names the file; the take keeps what was written "
               "and is not marked complete), or --out holds another device's takes (other "
               "channels, units or rate; said at its header, before any take). Exit 4: "
               "stdout cannot be written (a full disk).",
    )
    p.add_argument("--port", help="/dev/ttyACM0, sim://?texture=paper, socket://...; default: "
                   "the one likely pen attached (as tactile-run; tactile-ports lists them)")
    p.add_argument("--label", required=True, help="the texture being stroked, e.g. paper")
    p.add_argument("--out", required=True, type=path_given,
                   help="dataset folder (created if missing)")
    p.add_argument("--seconds", type=float_in(0.0), default=math.inf,
                   help="stop after this much data (a silence does not count: it waits for "
                        "the pen as long as it takes; `timeout 60 tactile-record ...` bounds "
                        "the wall time, its SIGTERM finishing the take)")
    p.add_argument("--baud", type=int_in(1), default=BAUD, help=f"UART baud rate (default {BAUD})")
    p.add_argument("--csv-rate", type=float_in(0.0), default=100.0,
                   help="rate of a CSV-line device, Hz (it declares none; default 100)")
    p.add_argument("--user", help="who is recording (the take's 'user': training's default "
                   "split keeps each user's takes in one part)")
    p.add_argument("--meta", action="append", default=[], metavar="KEY=VALUE",
                   help="more of the take's metadata, e.g. --meta session=2 (a whole number "
                   "is kept as one: test=session:1-3 selects it); repeatable")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_debug(p)
    return p


def take_extra(user: str | None, meta: list[str]) -> dict:
    """``--user`` and ``--meta KEY=VALUE`` as the take's extra JSON keys; an empty user, a key
    the recordings format uses itself, ``user`` or ``name`` (the selectors' file name) in
    ``--meta``, one given twice, or not KEY=VALUE is a :class:`ConfigError`."""
    from tactile.device.recordings.take_meta import RESERVED_KEYS
    from tactile.errors import ConfigError

    if user is not None and not user.strip():
        raise ConfigError("--user: give a name (or leave --user out)")
    extra: dict = {} if user is None else {"user": user}
    for item in meta:
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key):
            raise ConfigError(f"--meta {item!r}: expected KEY=VALUE (KEY: letters, digits, _)")
        if key in ("user", "name"):  # (training's selectors read name: as the file's name)
            raise ConfigError(f"--meta {key}: " + ("give it as --user" if key == "user" else
                                                   "selectors read name: as the take's file "
                                                   "name; choose another key"))
        if key in RESERVED_KEYS:
            raise ConfigError(f"--meta {key}: the recordings format's own key; choose another")
        if key in extra:
            raise ConfigError(f"--meta {key}: given twice")
        extra[key] = int(value) if re.fullmatch(r"-?[0-9]{1,18}", value) else value
    return extra


def _main(args: argparse.Namespace) -> int:
    from tactile.device.link.portlist import find_port
    from tactile.device.recordings.recorder import record
    from tactile.device.recordings.take import check_label, check_label_joins, dataset_folder
    from tactile.errors import DeviceError, RecordingError
    from tactile.postprocess.smoothing import UNCERTAIN

    check_label(args.label)  # before the port opens: a mistake costs no take
    extra = take_extra(args.user, args.meta)
    check_label_joins(args.out, args.label)  # (before looking for a pen, too)
    if args.label == UNCERTAIN:  # a take training would refuse
        raise RecordingError(f"label {UNCERTAIN!r}: the label stream reserves it for no stable "
                             "label, so a model cannot have that class: choose another")
    dataset_folder(args.out)
    auto = args.port is None  # found by auto-detection: after an unplug, look again
    if auto:
        args.port = find_port()
    res = record(
        args.port, args.label, args.out, args.seconds, args.baud, args.csv_rate,
        progress=not args.quiet, auto=auto, extra=extra,
    )
    for path in res.takes:
        print(path)
    st = res.stats
    print(
        f"tactile-record: {res.samples} samples in {len(res.takes)} take(s); gaps {res.gaps}"
        f" (lost {res.samples_lost}), errors crc {st.get('crc_errors')} malformed "
        f"{st.get('malformed')} csv {st.get('csv_rejected')}, reconnects {res.reconnects}"
        + (f"; {res.unrecorded} before any device header, not recorded" if res.unrecorded
           else ""),
        file=sys.stderr,
    )
    if not res.takes:
        if res.stopped_by and not st.get("bytes_in"):  # stopped, and the port was silent
            print(f"tactile-record: stopped by {res.stopped_by} before any data",
                  file=sys.stderr)
            return 0
        if st.get("bytes_in"):
            raise DeviceError(
                f"no take recorded from {args.port}: {st['bytes_in']} bytes read, "
                f"{st.get('samples', 0)} samples decoded, {res.unrecorded} of them before any "
                "device header and not recorded (a binary pen's samples need its header)")
        raise DeviceError(f"no data received from {args.port}")
    return 0


@command("tactile-record", guarded=True, files=True)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run("tactile-record", _main, args)


if __name__ == "__main__":
    sys.exit(main())
