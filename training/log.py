"""What training says and hears: diagnostics on stderr (:class:`Log`), and Ctrl-C and SIGTERM
(:class:`Stop`)."""

from __future__ import annotations

import signal
import sys
import threading

from tactile.cli import prefix, terminable_here
from tactile.training.dist import Dist


class Log:
    """Diagnostics on stderr. ``info`` only with progress on (and on rank 0); ``warn`` always
    (rank 0). ``bars``: tqdm bars on a terminal; elsewhere (a log file, CI) a plain line per
    epoch instead, never escape codes."""

    def __init__(self, progress: bool, main: bool = True) -> None:
        self.progress, self.main = progress and main, main
        self.bars = self.progress and sys.stderr.isatty()

    def info(self, msg: str) -> None:
        if self.progress:
            print(msg, file=sys.stderr, flush=True)

    def warn(self, msg: str) -> None:
        if self.main:
            print(f"{prefix()}warning: {msg}", file=sys.stderr, flush=True)


class Stop:
    """SIGINT while training: noted, and the loop stops at the next batch (``requested``),
    rolls back to the last finished epoch and saves. Used as a context manager around the
    epochs; outside it SIGINT is Python's KeyboardInterrupt. SIGTERM (``timeout``, ``kill``,
    a service manager or a batch scheduler stopping the job) does the same where the command
    took it (:func:`tactile.cli.terminable_here`: ``tactile-train`` of one process; under
    torchrun SIGTERM is how the agent ends the workers, and a script calling ``train`` keeps
    its own). ``signal``: the name of the signal that stopped it (None: none did)."""

    def __init__(self, dist: Dist) -> None:
        self.dist, self.flag, self.signal = dist, False, None
        self._old: dict = {}

    def __enter__(self) -> Stop:
        kinds = [signal.SIGINT]
        if threading.current_thread() is threading.main_thread() and terminable_here():
            kinds.append(signal.SIGTERM)
        self._old = {s: signal.signal(s, self._note) for s in kinds}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._old.items():
            signal.signal(s, handler)

    def _note(self, signum, frame) -> None:
        self.flag = True
        self.signal = self.signal or signal.Signals(signum).name

    def requested(self) -> bool:
        """Whether to stop now; under DDP every process agrees (any one's SIGINT stops all)."""
        return self.dist.any(self.flag)


__all__ = ["Log", "Stop"]
