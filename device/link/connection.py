"""The pen's port kept open: the one read/reconnect loop of every command that reads a pen live.

``tactile-run``, ``tactile-monitor``, ``tactile-record`` and ``tactile.runtime.labels`` read
through a :class:`Connection`::

    conn = Connection(LinkSettings(port), StreamDecoder(), stop, say)
    conn.open()
    while not stop["flag"]:
        chunk = conn.read()          # None: the pen is gone and the deadline or a stop came
        if chunk is None:
            break
        handle(chunk.events)         # decoder events, and Stall / Lost / Reconnected

It opens the port exclusively (:func:`~tactile.device.link.ports.open_port`), reads it with one read
of the device at a time (:func:`~tactile.device.link.ports.read_some`: the bytes that came with an
unplug are kept and decoded), feeds its decoder, and when the port vanishes reopens it with backoff,
taking back only the same pen (:func:`~tactile.device.link.ports.reconnect`: its header, its USB
serial number when known, under a new name when the pen was auto-detected or its old name went to
another device). What happened to the link comes back among the decoder's events, in order: a
:class:`Stall` once per silence, a :class:`Lost` when the port went, a :class:`Reconnected` before
the first bytes of the pen that came back.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import serial

from tactile.device.link.ports import (
    PenId,
    PortAbsent,
    PortBusy,
    open_port,
    read_some,
    reconnect,
    usb_serial,
    wait_for_port,
)
from tactile.device.protocol.decoder import StreamDecoder
from tactile.errors import ConfigError, DeviceError


@dataclass(frozen=True)
class Stall:
    """No data for ``seconds`` (the stall timeout passed): once per silence."""

    seconds: float


@dataclass(frozen=True)
class Lost:
    """The port vanished (unplugged); the next :meth:`Connection.read` looks for the pen."""

    port: str
    reason: str


@dataclass(frozen=True)
class Reconnected:
    """The same pen is back, on ``port``; the decoder was told (:meth:`StreamDecoder.reconnected`)
    before the events that follow. ``offline_s``: wall seconds from the port's loss until it was
    open again with the same pen's data coming (its probe included: up to a few seconds more
    than the cable was out); the samples' own count and clock cannot say (a pen that restarted
    counts again from zero, and the host's count goes on without a jump)."""

    port: str
    offline_s: float = 0.0


@dataclass(frozen=True)
class Chunk:
    """What one :meth:`Connection.read` got: the bytes read and the events, in order."""

    data: bytes = b""
    events: list = field(default_factory=list)


@dataclass(frozen=True)
class LinkSettings:
    """How a :class:`Connection` opens, watches and reopens its port.

    Attributes:
        port: a device path or pyserial URL.
        baud: the UART rate.
        auto: ``port`` was found by auto-detection: after an unplug the pen is also looked for
            among the likely pens listed (it may come back under another name).
        wait: an absent port at :meth:`Connection.open` is waited for (``tactile-run --wait``)
            instead of an error.
        reconnect: a lost port is reopened; False: the read after a :class:`Lost` raises.
        stall_timeout: seconds without data before a :class:`Stall`.
        status_every: seconds between "waiting for ..." lines while the pen is away.
        poll: seconds one read waits for data.
    """

    port: str
    baud: int = 115200
    auto: bool = False
    wait: bool = False
    reconnect: bool = True
    stall_timeout: float = 2.0
    status_every: float = 5.0
    poll: float = 0.05

    def __post_init__(self) -> None:
        if not isinstance(self.port, str) or not self.port:
            raise ConfigError(f"port {self.port!r}: must be a device path or a URL")
        if not (isinstance(self.baud, int) and self.baud > 0):
            raise ConfigError(f"baud {self.baud!r}: must be a whole number > 0")
        for name in ("stall_timeout", "status_every", "poll"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0):
                raise ConfigError(f"{name} {value!r}: must be a number of seconds > 0")


class Connection:
    """One pen's port: open, read, decode, reconnect to the same pen.

    Args:
        settings: the port and how to watch it.
        decoder: the stream's decoder; its last header (``decoder.info``) is what a reopened
            port must show to be taken for the pen.
        stop: ``stop["flag"]`` set (by a signal handler) ends any wait at once.
        say: gets the diagnostics, one line each (opened, lost, waiting, refused, stalled).
        deadline: ``time.monotonic()`` after which waiting for the pen gives up.
    """

    def __init__(
        self,
        settings: LinkSettings,
        decoder: StreamDecoder,
        stop: dict | None = None,
        say: Callable[[str], None] | None = None,
        deadline: float = math.inf,
    ) -> None:
        self.settings, self.decoder, self.deadline = settings, decoder, deadline
        self.stop = {"flag": False} if stop is None else stop
        self.say = say or (lambda _msg: None)
        self.port = settings.port  # the pen's name now (it may change at a reconnection)
        self.link: serial.SerialBase | None = None
        self.lost: Lost | None = None  # the port went and the pen is not back yet
        self.lost_at = 0.0  # time.monotonic() when it went
        self.usb: str | None = None  # the pen's USB serial number, when it has one
        self.reconnects = 0
        self.last_data = time.monotonic()
        self.stalled = False

    def open(self) -> bool:
        """Open the port (waiting for it with ``settings.wait``); False when stopped or out of
        time first. Raises :class:`~tactile.device.link.ports.PortBusy` when another program holds
        it, :class:`~tactile.errors.DeviceError` when it cannot be opened (now, without
        ``wait``, or ever)."""
        s = self.settings
        try:
            self.link = open_port(s.port, s.baud)
        except PortBusy:
            raise
        except PortAbsent as e:
            if not s.wait:
                raise
            self.say(f"{str(e).splitlines()[0]}; waiting for it")
            self.link = wait_for_port(s.port, s.baud, self.stop, self.say, self.deadline,
                                      "opened", s.status_every)
            if self.link is None:
                if not self.stop["flag"]:  # the deadline: said, as without --port
                    self.say(f"{s.port} did not open before the end of --seconds; stopping")
                return False
        else:
            self.say(f"opened {s.port}")
        self.usb = usb_serial(s.port)  # to find the pen again under another name
        self.last_data, self.stalled = time.monotonic(), False
        return True

    def read(self) -> Chunk | None:
        """Read once (waiting up to ``settings.poll`` s for data) and decode; after a
        :class:`Lost`, look for the pen first (blocking, with backoff, until it is back, a stop
        or the deadline). None: the pen did not come back before a stop or the deadline.
        Raises :class:`~tactile.errors.DeviceError` after a :class:`Lost` without
        ``settings.reconnect``."""
        if self.lost is not None:
            return self._reconnect()
        if self.link is None:
            raise DeviceError(f"{self.port}: not open")
        data, lost = read_some(self.link, wait=self.settings.poll)
        now = time.monotonic()
        events = self.decoder.feed(data) if data else []
        if data:
            if self.stalled:
                self.say(f"data again after a {now - self.last_data:.1f} s silence")
            self.last_data, self.stalled = now, False
        elif lost is None and not self.stalled and now - self.last_data > \
                self.settings.stall_timeout:
            self.stalled = True
            self.say(f"no data for {now - self.last_data:.1f} s")
            events.append(Stall(round(now - self.last_data, 1)))
        if lost is not None:
            self.say(f"port lost ({lost})" + ("; reconnecting" if self.settings.reconnect
                                               else ""))
            self.link.close()
            self.link = None
            self.lost = Lost(self.port, str(lost))
            self.lost_at = time.monotonic()
            events.append(self.lost)
        return Chunk(data, events)

    def chunks(self) -> Iterator[Chunk]:
        """The read loop: one :meth:`read` after another, each :class:`Chunk` yielded in order,
        until ``stop["flag"]`` is set or the deadline passes (both checked before each read), or
        the pen did not come back in time (:meth:`read` gave None). The caller may also leave
        the loop itself (``break``, or stop iterating): the port stays open until
        :meth:`close`. Raises what :meth:`read` raises."""
        while not self.stop["flag"] and time.monotonic() < self.deadline:
            chunk = self.read()
            if chunk is None:
                return
            yield chunk

    def silent_for(self, now: float | None = None) -> float | None:
        """Seconds of the current silence once it is a stall, else None."""
        if not self.stalled:
            return None
        return (time.monotonic() if now is None else now) - self.last_data

    def _reconnect(self) -> Chunk | None:
        s, lost = self.settings, self.lost
        if not s.reconnect:
            raise DeviceError(f"{lost.port}: lost ({lost.reason})")
        rate = self.decoder.csv_rate_hz
        got = reconnect(self.port, s.baud, PenId(self.decoder.info, self.usb),
                        lambda: StreamDecoder(csv_rate_hz=rate), self.stop, self.say,
                        self.deadline, s.status_every, s.auto, s.poll)
        if got is None:
            return None
        self.link, self.port, early = got
        self.lost = None
        self.reconnects += 1
        self.decoder.reconnected()
        self.last_data, self.stalled = time.monotonic(), False
        # what the probe read to check the header: the pen's data, decoded after the event
        offline = round(self.last_data - self.lost_at, 3)
        return Chunk(early, [Reconnected(self.port, offline), *self.decoder.feed(early)])

    def close(self) -> None:
        if self.link is not None:
            self.link.close()
            self.link = None

    def __enter__(self) -> Connection:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["Chunk", "Connection", "LinkSettings", "Lost", "Reconnected", "Stall"]
