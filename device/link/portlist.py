"""The serial ports attached, and which of them look like a pen.

One rule decides what looks like a pen (:func:`looks_like_pen`): ``tactile-run``,
``tactile-record`` and ``tactile-monitor`` use it (:func:`find_port`) when ``--port`` is omitted,
and ``tactile-ports`` shows it, so the listing says what those commands would pick.
"""

from __future__ import annotations

from dataclasses import dataclass

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


__all__ = ["PortRow", "find_port", "list_serial_ports", "looks_like_pen", "table"]
