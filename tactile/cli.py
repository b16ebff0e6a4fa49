"""What every command line shares: one-line errors, exit codes, ``--debug``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from tactile.errors import ConfigError, DeviceError, ModelContractError, TactileError

# Exit codes, documented in README.md: 0 ok, 1 bad input, 2 device/port, 3 model contract.
EXIT_OK, EXIT_USAGE, EXIT_DEVICE, EXIT_CONTRACT = 0, 1, 2, 3


def exit_code(err: BaseException) -> int:
    if isinstance(err, ModelContractError):
        return EXIT_CONTRACT
    if isinstance(err, DeviceError):
        return EXIT_DEVICE
    try:
        import serial

        if isinstance(err, serial.SerialException):
            return EXIT_DEVICE
    except ImportError:  # pragma: no cover
        pass
    return EXIT_USAGE


def run(prog: str, body: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Run ``body(args)``; a user's mistake becomes one line on stderr and a non-zero exit."""
    try:
        return body(args)
    except (TactileError, OSError, ValueError) as e:
        if getattr(args, "debug", False):
            raise
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return exit_code(e)


def add_debug(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--debug", action="store_true", help="show the full traceback on errors")


__all__ = ["ConfigError", "run", "add_debug", "exit_code", "EXIT_DEVICE", "EXIT_USAGE"]
