"""tactile.device.link: the serial link to a pen.

:mod:`~tactile.device.link.portlist` lists the ports and says which look like a pen;
:mod:`~tactile.device.link.ports` opens, reads and reopens one (a device path or any pyserial
URL, ``sim://`` included); :class:`Connection` is the one read/reconnect loop every command that
reads a pen live goes through.
"""

from tactile.device.link.connection import (
    Chunk,
    Connection,
    LinkSettings,
    Lost,
    Reconnected,
    Stall,
)
from tactile.device.link.portlist import PortRow, find_port, list_serial_ports, looks_like_pen
from tactile.device.link.ports import (
    PenId,
    PortAbsent,
    PortBusy,
    keep_trying,
    open_port,
    read_some,
    reconnect,
    wait_for_port,
)

__all__ = [
    "Chunk", "Connection", "LinkSettings", "Lost", "PenId", "PortAbsent", "PortBusy", "PortRow",
    "Reconnected", "Stall", "find_port", "keep_trying", "list_serial_ports", "looks_like_pen",
    "open_port", "read_some", "reconnect", "wait_for_port",
]
