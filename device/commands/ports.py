"""``tactile-ports``: the serial ports attached, and which of them look like a pen.

    tactile-ports            # a table: device, VID:PID, serial number, pen?, description
    tactile-ports --json     # the same as a JSON list
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict

from tactile.cli import Parser, add_debug, command, run


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-ports",
               description="List the serial ports and say which look like a pen (the one that "
               "tactile-run, tactile-record and tactile-monitor take when --port is omitted).")
    p.add_argument("--json", action="store_true", help="a JSON list instead of a table")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    from tactile.device.link.portlist import list_serial_ports, table

    rows = list_serial_ports()
    if args.json:
        print(json.dumps([asdict(r) for r in rows], indent=1))
    elif rows:
        print(table(rows))
    pens = [r.device for r in rows if r.likely_pen]
    if not rows:
        note = "no serial ports found"
    elif len(pens) == 1:
        note = f"one likely pen: {pens[0]} (taken when --port is omitted)"
    elif pens:
        note = f"{len(pens)} likely pens: give --port"
    else:
        note = "no likely pen (no USB serial device): give --port"
    print(f"tactile-ports: {note}", file=sys.stderr)
    return 0


@command("tactile-ports")
def main(argv: list[str] | None = None) -> int:
    return run("tactile-ports", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
