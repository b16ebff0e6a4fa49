"""Opening a serial port (a device path or any pyserial URL) and waiting for one to come back.

Shared by the recorder and the runtime: both keep going when the cable is pulled, and both
must tell a port that is absent for now (worth waiting for) from one that can never open.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable
from typing import TypeVar

import serial

from tactile.errors import DeviceError

T = TypeVar("T")


class PortAbsent(DeviceError):
    """The port cannot be opened now (no such device yet, unplugged, connection refused):
    worth waiting for, unlike a name that can never open (a bad URL or option)."""


def open_port(port: str, baud: int, timeout: float = 0.05) -> serial.SerialBase:
    """Open ``port``; :class:`PortAbsent` or :class:`DeviceError` (one line, naming it)."""
    try:
        return serial.serial_for_url(port, baudrate=baud, timeout=timeout)
    except (ValueError, serial.SerialException) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        # pyserial names the port in some messages ("[Errno 2] could not open port P: ...")
        msg = re.sub(r"^.*could not open port .*?: (?=\[Errno)", "", msg)
        kind = PortAbsent if isinstance(e, serial.SerialException) else DeviceError
        raise kind(f"cannot open {port}: {msg}") from None


def keep_trying(
    attempt: Callable[[], T | None],
    stop: dict,
    say: Callable[[str], None],
    what: str,
    deadline: float = math.inf,
    status_every: float = 5.0,
    delays: tuple[float, float] = (0.1, 2.0),
) -> T | None:
    """Call ``attempt()`` until it returns something, ``stop["flag"]`` is set or ``deadline``
    (``time.monotonic()``) passes (None in the last two cases). Between tries it waits
    ``delays[0]`` s, doubling up to ``delays[1]``, in short naps so that a stop or the deadline
    is acted on at once; ``say`` gets "waiting for <what> for N s" every ``status_every`` s."""
    delay, longest = delays
    since = last_status = time.monotonic()
    while not stop["flag"] and time.monotonic() < deadline:
        got = attempt()
        if got is not None:
            return got
        until = min(time.monotonic() + delay, deadline)
        while not stop["flag"] and time.monotonic() < until:
            time.sleep(0.05)
        delay = min(delay * 2, longest)
        if time.monotonic() - last_status >= status_every:
            last_status = time.monotonic()
            say(f"waiting for {what} for {last_status - since:.0f} s")
    return None


def wait_for_port(
    port: str,
    baud: int,
    stop: dict,
    say: Callable[[str], None],
    deadline: float = math.inf,
    verb: str = "reconnected to",
    status_every: float = 5.0,
    timeout: float = 0.05,
) -> serial.SerialBase | None:
    """Reopen ``port`` with backoff (0.1 s doubling to 2 s, :func:`keep_trying`) until it
    opens, ``stop["flag"]`` is set or ``deadline`` passes; None in the last two cases. A port
    that can never open raises its :class:`DeviceError` at once. ``say`` gets one line when the
    port opens and one every ``status_every`` s while waiting."""

    def attempt() -> serial.SerialBase | None:
        try:
            return open_port(port, baud, timeout)
        except PortAbsent:
            return None

    link = keep_trying(attempt, stop, say, port, deadline, status_every)
    if link is not None:
        say(f"{verb} {port}")
    return link
