"""The serial ports attached, which of them look like a pen, and ``tactile-ports``.

    tactile-ports            # a table: device, VID:PID, serial number, pen?, description
    tactile-ports --json     # the same as a JSON list

One rule decides what looks like a pen (:func:`looks_like_pen`): ``tactile-run``,
``tactile-record`` and ``tactile-monitor`` use it (:func:`find_port`) when ``--port`` is omitted,
and ``tactile-ports`` shows it, so the listing says what those commands would pick.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass

from tactile.cli import Parser, add_debug, run
from tactile.errors import DeviceError


def looks_like_pen(port) -> bool:
    """A USB serial device: it has a USB vendor id, or a ttyACM/ttyUSB-style name (a
    ``serial.tools.list_ports`` entry, or anything with ``.device`` and ``.vid``)."""
    return port.vid is not None or "ACM" in port.device or "USB" in port.device


@dataclass(frozen=True)
class PortRow:
    """One serial port as ``tactile-ports`` shows it."""

    device: str
    description: str
    vid_pid: str | None  # "2886:8045" (hex), None for a device that is not USB
    serial_number: str | None
    manufacturer: str | None
    likely_pen: bool


def list_serial_ports() -> list[PortRow]:
    """The serial ports attached, sorted by device name."""
    from serial.tools import list_ports

    rows = []
    for p in list_ports.comports():
        vid, pid = getattr(p, "vid", None), getattr(p, "pid", None)
        rows.append(PortRow(
            device=p.device,
            description=getattr(p, "description", None) or "n/a",
            vid_pid=None if vid is None else f"{vid:04x}:{(pid or 0):04x}",
            serial_number=getattr(p, "serial_number", None),
            manufacturer=getattr(p, "manufacturer", None),
            likely_pen=looks_like_pen(p),
        ))
    return sorted(rows, key=lambda r: r.device)


def find_port(wait: bool = False) -> str | None:
    """The one likely pen among the serial devices (:func:`looks_like_pen`), or a DeviceError
    listing the candidates. With ``wait``, no likely pen is not an error: it returns None, for
    the caller to look again."""
    from serial.tools import list_ports

    ports = list(list_ports.comports())
    likely = [p for p in ports if looks_like_pen(p)]
    if len(likely) == 1:
        return likely[0].device
    if wait and not likely:
        return None
    listing = ", ".join(f"{p.device} ({p.description})" for p in ports) or "none"
    raise DeviceError(
        f"{'no' if not likely else 'more than one'} likely pen found; give --port "
        f"(serial devices: {listing})"
    )


def table(rows: list[PortRow]) -> str:
    """The rows as aligned text columns, a heading first."""
    head = ("DEVICE", "VID:PID", "SERIAL", "PEN", "DESCRIPTION")
    cells = [head] + [(r.device, r.vid_pid or "-", r.serial_number or "-",
                       "yes" if r.likely_pen else "no", r.description) for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(head) - 1)]
    return "\n".join("  ".join([*(c[i].ljust(widths[i]) for i in range(len(widths))), c[-1]])
                     for c in cells)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-ports",
               description="List the serial ports and say which look like a pen (the one that "
               "tactile-run, tactile-record and tactile-monitor take when --port is omitted).")
    p.add_argument("--json", action="store_true", help="a JSON list instead of a table")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
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


def main(argv: list[str] | None = None) -> int:
    return run("tactile-ports", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
