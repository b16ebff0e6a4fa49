"""pyserial URL handler for the simulated pen: ``serial.serial_for_url("sim://?texture=paper")``.

pyserial finds it because :mod:`tactile.device` appends itself to
``serial.protocol_handler_packages``. Options are those of
:class:`~tactile.device.simlink.LinkConfig`; ``speed=max`` serves bytes as fast as they are read.
"""

from __future__ import annotations

import math
import threading
import time
from urllib.parse import urlsplit

import serial
from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from tactile.device.simlink import LinkConfig, PenLink
from tactile.errors import ConfigError

# Unplug state shared by every instance, keyed by URL: a reopened port must stay unopenable
# until the "cable" is back, and the pen must not be unplugged a second time.
_UNPLUGGED: dict[str, dict] = {}
_LOCK = threading.Lock()


class Serial(SerialBase):
    """A serial port whose other end is a simulated pen."""

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        self.config = self.from_url(self._port)  # a bad option: ConfigError, a ValueError
        restart_at = 0.0
        with _LOCK:
            state = _UNPLUGGED.get(self._port)
        if state is not None:
            if time.monotonic() < state["back_at"]:
                raise SerialException(
                    f"could not open port {self._port}: [Errno 2] No such file or directory"
                )
            restart_at = state["resume_s"]
        self.link = PenLink(self.config, restart_at_s=restart_at)
        self._buf = bytearray()
        self._t0 = time.monotonic()
        self._stream0 = self.link.stream_time  # after a replug the motion has moved on
        self._silent_until = 0.0
        self._stalls_seen = 0
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
        if cfg.unplug and self._port not in _UNPLUGGED and self.link.stream_time >= cfg.unplug[0]:
            with _LOCK:
                _UNPLUGGED[self._port] = {
                    "back_at": now + cfg.unplug[1],  # the cable is out for D wall seconds
                    "resume_s": self.link.stream_time + cfg.unplug[1],
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
        if self.link.injected.stalled_samples and not self._stalls_seen:
            self._stalls_seen = 1
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


__all__ = ["Serial", "forget_unplugs", "serial"]
