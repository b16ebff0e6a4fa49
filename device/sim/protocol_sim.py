"""pyserial URL handler for the simulated pen: ``serial.serial_for_url("sim://?texture=paper")``.

pyserial finds it because :mod:`tactile.device` appends ``tactile.device.sim`` to
``serial.protocol_handler_packages`` (pyserial imports ``<package>.protocol_<scheme>``). Options
are those of :class:`~tactile.device.sim.simlink.LinkConfig`; ``speed=max`` serves bytes as fast
as they are read.
"""

from __future__ import annotations

import math
import threading
import time
from urllib.parse import urlsplit

import serial
from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from tactile.device.sim.simlink import LinkConfig, PenLink
from tactile.errors import ConfigError

# Unplug state shared by every instance, keyed by URL: a reopened port must stay unopenable
# until the "cable" is back, and then continues the same pen (its stream, its fault schedule).
_UNPLUGGED: dict[str, dict] = {}
_LAST: dict[str, PenLink] = {}  # the link each URL opened last (last_link)
_LOCK = threading.Lock()


class Serial(SerialBase):
    """A serial port whose other end is a simulated pen."""

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        self.config = self.from_url(self._port)  # a bad option: ConfigError, a ValueError
        with _LOCK:
            state = _UNPLUGGED.get(self._port)
            if state is not None:
                if time.monotonic() < state["back_at"]:
                    raise SerialException(
                        f"could not open port {self._port}: [Errno 2] No such file or directory"
                    )
                del _UNPLUGGED[self._port]
                self.link = state["link"]  # the same pen, rebooted: its stream goes on
                self.link.restart(state["resume_s"])
            else:
                self.link = PenLink(self.config, trace=TRACE)
            _LAST[self._port] = self.link
        self._buf = bytearray()
        self._t0 = time.monotonic()
        self._stream0 = self.link.stream_time  # after a replug the motion has moved on
        self._silent_until = 0.0
        self._stalls_seen = self.link.injected.stalls
        self.is_open = True

    def from_url(self, url: str) -> LinkConfig:
        parts = urlsplit(url)
        if parts.scheme != "sim":
            raise ConfigError(f"expected a sim:// URL, got {url!r}")
        if parts.netloc or parts.path not in ("", "/"):
            raise ConfigError(f"{url!r}: options go after '?', e.g. sim://?texture=paper&seed=3")
        return LinkConfig.from_query(parts.query)

    def _reconfigure_port(self) -> None:  # baud rate etc. mean nothing to the simulated pen
        pass

    def close(self) -> None:
        self.is_open = False

    # -- data -------------------------------------------------------------------------------------

    def _pump(self) -> None:
        """Move due bytes from the pen into the receive buffer; raise if unplugged."""
        cfg = self.config
        now = time.monotonic()
        # the unplug comes once the port has handed over what the pen sent before it (at
        # speed=max the port runs ahead of the reader; a real port holds a few samples at most)
        out_for = None if self._buf else self.link.unplug_due()
        if out_for is not None:
            with _LOCK:
                _UNPLUGGED[self._port] = {
                    "back_at": now + out_for,  # the cable is out for D wall seconds
                    "resume_s": self.link.stream_time + out_for,
                    "link": self.link,
                }
            self.is_open = False
            raise SerialException(
                "device reports readiness to read but returned no data "
                "(device disconnected or multiple access on port?)"
            )
        if now < self._silent_until or self.link.finished:
            return
        if math.isinf(cfg.speed):
            # at least one whole frame (produce() makes whole frames only), so a read of
            # 4096 bytes never waits for its timeout on a nearly full buffer
            want = max(cfg.per_frame, max(0, 4096 - len(self._buf)) // 16 + 1)
        else:
            due_s = self._stream0 + (now - self._t0) * cfg.speed
            want = int((due_s - self.link.stream_time) * cfg.rate)
        if want > 0:
            self._buf += self.link.produce(want)
        if self.link.injected.stalls > self._stalls_seen:  # a stall began: silence for D
            self._stalls_seen = self.link.injected.stalls
            self._silent_until = now + cfg.stall[1] / (1.0 if math.isinf(cfg.speed) else cfg.speed)

    @property
    def in_waiting(self) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        self._pump()
        return len(self._buf)

    def read(self, size: int = 1) -> bytes:
        if not self.is_open:
            raise PortNotOpenError()
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        while True:
            self._pump()
            if len(self._buf) >= size:
                break
            if deadline is not None and time.monotonic() >= deadline:
                break
            if self.link.finished and not self._buf and deadline is None:
                break  # the pen has stopped for good: do not block forever
            time.sleep(0.002)
        data = bytes(self._buf[:size])
        del self._buf[:size]
        return data

    def write(self, data: bytes) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        return len(data)  # the pen takes no commands

    def reset_input_buffer(self) -> None:
        self._buf.clear()

    def reset_output_buffer(self) -> None:
        pass


def forget_unplugs() -> None:
    """Clear the shared unplug state (tests use it to reuse a URL)."""
    with _LOCK:
        _UNPLUGGED.clear()
        _LAST.clear()


TRACE = False
"""Set True before opening to have each new link trace its ground truth (benchmarks)."""


def last_link(url: str) -> PenLink | None:
    """The :class:`~tactile.device.sim.simlink.PenLink` behind the port ``url`` opened last (the
    same one across replugs): its ``injected`` counts and, with :data:`TRACE`, its trace."""
    with _LOCK:
        return _LAST.get(url)


__all__ = ["Serial", "forget_unplugs", "last_link", "serial"]
