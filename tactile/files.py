"""Files a command writes whole or not at all, and what a write that failed is."""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

from tactile.cli import FULL_DISK
from tactile.errors import ConfigError, OutputError


def write_all(fd: int, data: bytes | memoryview) -> None:
    """``os.write`` until all of ``data`` is written (a regular file may take part of it)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def replace_file(path: Path, data: bytes | memoryview) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file beside it, fsynced, renamed over
    it. A write that fails leaves no temporary file and raises its ``OSError``."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


def output_error(what: str, e: OSError) -> ConfigError | OutputError:
    """The error of an output that could not be written: :class:`OutputError` (exit 4) for a
    full disk, where freeing space may be all it takes, else :class:`ConfigError` (exit 1: a
    path that cannot take the file)."""
    return (OutputError if e.errno in FULL_DISK else ConfigError)(f"{what} ({e.strerror or e})")


def write_whole(path: Path, data: bytes | memoryview) -> None:
    """:func:`replace_file`, a failure one error naming ``path`` (:func:`output_error`)."""
    try:
        replace_file(path, data)
    except OSError as e:
        raise output_error(f"{path}: cannot write", e) from None


def figure_bytes(fig, fmt: str, dpi: int) -> bytes:
    """A matplotlib figure drawn in memory as ``fmt`` (``png``, ``pdf``, ...): written with
    :func:`write_whole`, a full disk leaves no cut-short image."""
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=dpi)
    return buf.getvalue()


__all__ = ["figure_bytes", "output_error", "replace_file", "write_all", "write_whole"]
