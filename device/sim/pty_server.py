"""The simulated pen on a pseudo-terminal (``tactile-sim --pty``): any program that opens a
serial device reads it as it would a real pen."""

from __future__ import annotations

import math
import os
import signal
import sys
import time
import tty

from tactile.device.sim.simlink import LinkConfig, PenLink
from tactile.errors import ConfigError


def serve_pty(config: LinkConfig) -> None:
    """Stream the pen on a new pseudo-terminal until SIGINT/SIGTERM or ``seconds`` ran out;
    its path is printed on stdout (as it is at the call)."""
    if config.unplug:
        raise ConfigError("unplug is only simulated on sim:// ports (a pty cannot vanish)")
    if math.isinf(config.speed):
        raise ConfigError("a pty streams in (scaled) real time: give --speed as a number")
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    print(os.ttyname(slave), file=sys.stdout, flush=True)
    link = PenLink(config)
    stop = {"flag": False}
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *_: stop.__setitem__("flag", True))
    t0 = time.monotonic()
    dropped = 0
    silent_until = 0.0
    try:
        while not stop["flag"] and not link.finished:
            now = time.monotonic()
            due = int(((now - t0) * config.speed - link.stream_time) * config.rate)
            if due > 0 and now >= silent_until:
                stalled = link.injected.stalled_samples
                data = link.produce(due)
                if link.injected.stalled_samples != stalled:
                    silent_until = now + config.stall[1] / config.speed
                try:
                    # a full buffer takes part of the bytes or none: a UART drops the rest
                    dropped += len(data) - os.write(master, data)
                except BlockingIOError:  # nobody reads: a UART drops, so do we
                    dropped += len(data)
            time.sleep(0.005)
    finally:
        print(f"tactile-sim: {link.injected.samples} samples, {dropped} bytes unread",
              file=sys.stderr)
        os.close(master)
        os.close(slave)


__all__ = ["serve_pty"]
