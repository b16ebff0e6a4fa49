"""Files a command writes whole or not at all."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from tactile.cli import FULL_DISK
from tactile.errors import ConfigError, OutputError


def write_whole(path: Path, data: bytes | memoryview) -> None:
    """Write ``data`` to ``path`` whole or not at all: into a temporary file beside it,
    fsynced, renamed over it. A write that fails leaves no temporary file and is one error
    naming ``path``: :class:`OutputError` (exit 4) for a full disk, where freeing space may be
    all it takes, else :class:`ConfigError` (exit 1: a path that cannot take a file)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        kind = OutputError if e.errno in FULL_DISK else ConfigError
        raise kind(f"{path}: cannot write ({e.strerror or e})") from None


__all__ = ["write_whole"]
