"""How the long-running commands stop cleanly: SIGINT and SIGTERM set a flag the loops read."""

from __future__ import annotations

import signal
from collections.abc import Callable

from tactile.cli import started


def stop_on_signals(say: Callable[[str], None]) -> dict | None:
    """From now on, SIGINT and SIGTERM set ``stop["flag"]`` instead of ending the process: the
    read loops (:meth:`~tactile.device.link.connection.Connection.chunks`, the waits for a pen,
    :func:`~tactile.runtime.runner.replay`) check it and end, and the command finishes as
    usual. Returns ``stop`` (``{"flag": False}``; ``stop["by"]``: the first signal's name, once
    one came), or None when a signal came while the command was starting
    (``tactile.cli.command(guarded=True)``): ``say`` then gets the line that says so, and the
    command stops without reading."""
    stop: dict = {"flag": False}

    def note(signum, frame) -> None:
        stop["flag"] = True
        stop.setdefault("by", signal.Signals(signum).name)

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, note)
    early = started()  # after our handlers are in place: no signal falls between the two
    if early:
        say(f"stopped by {early} while starting")
        return None
    return stop


__all__ = ["stop_on_signals"]
