"""What training says and hears: diagnostics on stderr (:class:`Log`) and Ctrl-C (:class:`Stop`)."""

from __future__ import annotations

import signal
import sys

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
            print(f"warning: {msg}", file=sys.stderr, flush=True)


class Stop:
    """SIGINT while training: noted, and the loop stops at the next batch (``requested``),
    rolls back to the last finished epoch and saves. Used as a context manager around the
    epochs; outside it SIGINT is Python's KeyboardInterrupt."""

    def __init__(self, dist: Dist) -> None:
        self.dist, self.flag, self._old = dist, False, None

    def __enter__(self) -> Stop:
        self._old = signal.signal(signal.SIGINT, self._note)
        return self

    def __exit__(self, *exc) -> None:
        signal.signal(signal.SIGINT, self._old)

    def _note(self, signum, frame) -> None:
        self.flag = True

    def requested(self) -> bool:
        """Whether to stop now; under DDP every process agrees (any one's SIGINT stops all)."""
        return self.dist.any(self.flag)


__all__ = ["Log", "Stop"]
