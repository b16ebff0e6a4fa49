"""Opening, reading and reopening a serial port (a device path or any pyserial URL).

Shared by the recorder and the runtime: both keep going when the cable is pulled, both must tell
a port that is absent for now (worth waiting for) from one that can never open or that another
program holds, both must keep every byte that arrived before an unplug, and both must come back
only to the same pen.

* :func:`open_port` opens a port for exclusive use (pyserial's ``exclusive=True``: an advisory
  ``flock`` on a posix device; URL handlers such as ``socket://`` and ``loop://`` ignore it) and
  non-blocking (``timeout=0``), keeps the bytes that arrived while it opened (pyserial's open
  discards them), and names the program that holds a busy port.
* :func:`read_some` waits for data and then makes exactly one read of the device: pyserial's
  ``read(n)`` with a timeout keeps reading until ``n`` bytes or the timeout, and when the
  device errors midway (an unplug) it raises and discards what it had read, up to ``n - 1``
  bytes. With ``timeout=0`` its posix and socket reads make one ``os.read``/``recv`` and return.
* :func:`reconnect` reopens the port (or the pen under a new name, found by its USB serial
  number or among the likely pens listed) and accepts it only when its header shows the same
  pen (:class:`PenId`).

:class:`~tactile.device.link.connection.Connection` is the loop built on these that every command
reading a pen live uses.
"""

from __future__ import annotations

import errno
import math
import os
import re
import select
import time
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import serial

from tactile.device.link.portlist import looks_like_pen
from tactile.device.protocol.decoder import Header, StreamDecoder
from tactile.device.protocol.info import DeviceInfo
from tactile.errors import DeviceError, TactileError

T = TypeVar("T")

LOST = (serial.SerialException, OSError)
"""What a read raises when the port vanished (pyserial wraps most ``OSError``; not all)."""

PROBE_S = 3.0  # how long a reopened port has to show its header (the pen sends one a second)
PROBE_BYTES = 1 << 16  # ... and how many bytes it may send without one
IDLE_POLL_S = 0.005  # how often read_some looks at a port it cannot wait on (loop://, sim://)


class PortAbsent(DeviceError):
    """The port cannot be opened now (no such device yet, unplugged, connection refused):
    worth waiting for, unlike a name that can never open (a bad URL or option)."""


class PortBusy(PortAbsent):
    """Another program holds the port (its exclusive lock)."""


def holders(port: str) -> list[str]:
    """The processes holding ``port``'s exclusive lock, as ``"pid N (command line)"``, from
    ``/proc/locks`` (empty where there is none, or when they are hidden from us)."""
    try:
        st = os.stat(port)
        inode = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
        with open("/proc/locks") as f:
            pids = [p[4] for p in (ln.split() for ln in f)
                    if len(p) > 5 and p[1] == "FLOCK" and p[5] == inode]
    except OSError:
        return []
    found = []
    for pid in dict.fromkeys(pids):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:  # gone, or not ours to look at
            cmd = ""
        found.append(f"pid {pid} ({cmd[:120]})" if cmd else f"pid {pid}")
    return found


def _keep_input() -> None:
    """Stands in for a port's ``reset_input_buffer`` while it opens (:func:`open_port`)."""


def open_port(port: str, baud: int) -> serial.SerialBase:
    """Open ``port`` exclusively and non-blocking (read it with :func:`read_some`).

    Raises :class:`PortBusy` when another program holds it (naming it when ``/proc`` shows
    it), :class:`PortAbsent` when it cannot be opened now, :class:`DeviceError` when it never
    can; each a line naming the port."""
    if port.lower().startswith("socket://"):  # pyserial's own line for a bad one names nothing
        parts = urllib.parse.urlsplit(port)
        try:
            number = parts.port
        except ValueError:
            number = None
        if not parts.hostname or number is None:
            raise DeviceError(f"cannot open {port}: expected socket://HOST:PORT, PORT a number "
                              "0-65535")
    try:
        link = serial.serial_for_url(port, baudrate=baud, timeout=0, exclusive=True,
                                     do_not_open=True)
        # pyserial's open() ends by discarding the input that has arrived (a posix port's
        # tcflush by its private _reset_input_buffer, a socket's recv until empty by the public
        # one): a device that sends as soon as the link is up (a pen that boots when plugged
        # in, one behind a TCP bridge, a burst it held while the link was down) would lose
        # those samples and its header with them; the decoder finds frames in any bytes
        hooks = [n for n in ("reset_input_buffer", "_reset_input_buffer") if hasattr(link, n)]
        for name in hooks:
            setattr(link, name, _keep_input)
        try:
            link.open()
        finally:
            for name in hooks:
                delattr(link, name)
        return link
    except (ValueError, serial.SerialException) as e:
        if getattr(e, "errno", None) in (errno.EWOULDBLOCK, errno.EAGAIN):  # the flock failed
            who = holders(port)
            raise PortBusy(f"cannot open {port}: in use by "
                           f"{', '.join(who) if who else 'another program'}") from None
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        # pyserial names the port in some messages ("[Errno 2] could not open port P: ...")
        msg = re.sub(r"^.*could not open port .*?: (?=\[Errno)", "", msg)
        kind = PortAbsent if isinstance(e, serial.SerialException) else DeviceError
        raise kind(f"cannot open {port}: {msg}") from None


def read_some(
    link: serial.SerialBase, limit: int = 4096, wait: float = 0.05
) -> tuple[bytes, Exception | None]:
    """Wait up to ``wait`` s for data on a port from :func:`open_port`, then read what is there
    (at most ``limit`` bytes) in one read of the device.

    Returns ``(data, lost)``: ``lost`` is the exception when the port failed (unplugged), and
    ``data`` is then whatever came before it: no byte that was read is dropped. Ports with a
    file descriptor (devices, ptys, ``socket://``) are waited on with ``select``; the others
    (``loop://``, ``sim://``) are looked at every 5 ms."""
    try:
        fd = link.fileno()
    except (AttributeError, NotImplementedError, ValueError):
        fd = None
    try:
        if fd is not None:
            if not select.select([fd], [], [], wait)[0]:
                return b"", None
            return link.read(limit), None  # timeout 0: one os.read / recv
        deadline = time.monotonic() + wait
        while True:
            data = link.read(limit)
            if data or time.monotonic() >= deadline:
                return data, None
            time.sleep(IDLE_POLL_S)
    except LOST as e:
        return b"", e


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
) -> serial.SerialBase | None:
    """Reopen ``port`` with backoff (0.1 s doubling to 2 s, :func:`keep_trying`) until it
    opens, ``stop["flag"]`` is set or ``deadline`` passes; None in the last two cases. A port
    that can never open raises its :class:`DeviceError` at once. ``say`` gets one line when the
    port opens and one every ``status_every`` s while waiting."""

    def attempt() -> serial.SerialBase | None:
        try:
            return open_port(port, baud)
        except PortAbsent:
            return None

    link = keep_trying(attempt, stop, say, port, deadline, status_every)
    if link is not None:
        say(f"{verb} {port}")
    return link


# -- the same pen, and only it ------------------------------------------------------------------


def usb_serial(port: str) -> str | None:
    """The USB serial number of the device ``port`` names (a path or a symlink to it, such as
    ``/dev/serial/by-id/...``), from ``serial.tools.list_ports``; None for a URL, a pty or a
    device without one."""
    if "://" in port:
        return None
    from serial.tools import list_ports

    target = os.path.realpath(port)
    for p in list_ports.comports():
        if os.path.realpath(p.device) == target:
            return p.serial_number or None
    return None


@dataclass(frozen=True)
class PenId:
    """What a reopened port must show to be taken for the pen that was unplugged.

    ``info`` is the pen's last header as the decoder reported it (None before any: then any
    device that opens under the port's name is taken, as nothing tells pens apart yet), and
    ``usb`` its USB serial number. A binary pen's header must be equal in every field (device
    string, channels with units and scales, rate, protocol version). A CSV-line device sends no
    header (a names line at most, and only when it restarts), so it must give rows of the same
    number of channels, at the same configured rate.
    """

    info: DeviceInfo | None = None
    usb: str | None = None

    def differs(self, info: DeviceInfo) -> str | None:
        """None when ``info`` is this pen's, else what differs (one short phrase)."""
        mine = self.info
        if mine is None:
            return None
        if mine.device == "csv" or info.device == "csv":
            if info.device != mine.device:
                return f"a {info.device!r} device, not the {mine.device!r} one"
            if len(info.channels) != len(mine.channels):
                return f"{len(info.channels)} CSV channels, not {len(mine.channels)}"
            return None if info.sample_rate_hz == mine.sample_rate_hz else "another rate"
        if info == mine:
            return None
        if info.device != mine.device:
            return f"device {info.device!r}, not {mine.device!r}"
        if info.channels != mine.channels:
            return f"channels {list(info.channel_names)}, not {list(mine.channel_names)} " \
                   "(or other units or scales)"
        return f"rate {info.sample_rate_hz:g} Hz / protocol {info.protocol_version}, not " \
               f"{mine.sample_rate_hz:g} Hz / {mine.protocol_version}"


@dataclass(frozen=True)
class Probe:
    """What :func:`probe` found on a reopened port."""

    why: str | None = None  # why it is not the pen; None: it is
    data: bytes = b""  # the bytes read, when it is the pen (the caller decodes them)
    other: bool = False  # it showed another device (a header), not merely nothing yet


def probe(
    link: serial.SerialBase,
    pen: PenId,
    new_decoder: Callable[[], StreamDecoder],
    stop: dict,
    wait: float = 0.05,
    seconds: float = PROBE_S,
) -> Probe:
    """Read a reopened port until its first header (at most ``seconds`` or
    :data:`PROBE_BYTES`) and compare it with ``pen``. Same pen: the bytes read come back in
    :attr:`Probe.data` (the caller feeds them to its own decoder: nothing is lost)."""
    if pen.info is None:
        return Probe()
    dec = new_decoder()
    got = bytearray()
    until = time.monotonic() + seconds
    while not stop["flag"] and time.monotonic() < until and len(got) < PROBE_BYTES:
        data, lost = read_some(link, wait=wait)
        got += data
        try:
            events = dec.feed(data) if data else []
        except TactileError as e:  # a decoder that gives up on these bytes: not our pen
            return Probe(f"unreadable ({e})", other=True)
        # a header, or a CSV board's rows waiting for a names line (known by their width)
        shown = [ev.info for ev in events if isinstance(ev, Header)] or [
            i for i in (dec.waiting_info,) if i is not None]
        if shown:
            why = pen.differs(shown[0])
            return Probe(data=bytes(got)) if why is None else Probe(why, other=True)
        if lost is not None:
            return Probe(f"lost again ({lost})")
    if stop["flag"]:
        return Probe("stopped")
    return Probe(f"no header in {time.monotonic() - until + seconds:.1f} s ({len(got)} B)")


def _key(name: str) -> str:
    """What two names of one device have in common (a URL is its own)."""
    return name if "://" in name else os.path.realpath(name)


def reconnect(
    port: str,
    baud: int,
    pen: PenId,
    new_decoder: Callable[[], StreamDecoder],
    stop: dict,
    say: Callable[[str], None],
    deadline: float = math.inf,
    status_every: float = 5.0,
    detect: bool = False,
    wait: float = 0.05,
) -> tuple[serial.SerialBase, str, bytes] | None:
    """Reopen the pen after an unplug: ``(link, its name, the bytes its probe read)``, or None
    when ``stop["flag"]`` is set or ``deadline`` passes first.

    Candidates, tried with backoff (0.1 s doubling to 2 s): ``port`` itself; the devices listed
    with the pen's USB serial number (``pen.usb``: it came back under another name); and, with
    ``detect`` (the pen was found by auto-detection) or once ``port`` has shown another device,
    every likely pen listed (:func:`~tactile.device.link.portlist.looks_like_pen`; only when there
    is one, as at start, before the pen's header is known). A device listed with another USB
    serial number than the pen's is not opened. Each one that opens must show the pen's header
    (:func:`probe`); one that does not is closed and said once; ``port`` is looked at again
    later (it may be the pen, still starting), another name that showed another device only
    once it has left the listing and come back. A busy port is waited for, the holder said
    once. A port that can never open raises its :class:`DeviceError` at once."""
    from serial.tools import list_ports

    said: set[str] = set()
    others: set[str] = set()  # detected names that showed another device, while listed
    look_around = [detect]

    def once(msg: str) -> None:
        if msg not in said:
            said.add(msg)
            say(msg)

    def candidates() -> tuple[list[str], dict[str, str]]:
        listed = [(p, getattr(p, "serial_number", None)) for p in list_ports.comports()]
        numbers = {_key(p.device): n for p, n in listed if n}
        names = [port]
        if pen.usb:
            names += [p.device for p, n in listed if n == pen.usb]
        if look_around[0]:
            likely = [p.device for p, _ in listed if looks_like_pen(p)]
            names += likely if pen.info is not None or len(likely) == 1 else []
        others.intersection_update(p.device for p, _ in listed)
        return [n for n in dict.fromkeys(names) if n == port or n not in others], numbers

    def attempt() -> tuple[serial.SerialBase, str, bytes] | None:
        names, numbers = candidates()
        for name in names:
            number = numbers.get(_key(name))
            if pen.usb and number and number != pen.usb:
                found = Probe(f"USB serial number {number}, not {pen.usb}", other=True)
            else:
                try:
                    link = open_port(name, baud)
                except PortBusy as e:
                    once(str(e))
                    continue
                except PortAbsent:
                    continue
                left = max(0.0, min(PROBE_S, deadline - time.monotonic()))
                found = probe(link, pen, new_decoder, stop, wait, left)
                if found.why is None:
                    return link, name, found.data
                link.close()
                if found.why == "stopped":
                    return None
            once(f"{name} is not the pen: {found.why}; still looking")
            if found.other and name == port:  # its name went to another device: look around
                look_around[0] = True
            elif found.other:
                others.add(name)
        return None

    got = keep_trying(attempt, stop, say, "the pen" if pen.info else port, deadline,
                      status_every)
    if got is not None:
        say(f"reconnected to {got[1]}")
    return got
