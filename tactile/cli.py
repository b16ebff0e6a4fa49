"""What every command line shares: one-line errors, exit codes, ``--debug``."""

from __future__ import annotations

import argparse
import importlib
import math
import os
import signal
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
    except BrokenPipeError:  # the reader of stdout went away (`| head`): stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so that the interpreter's final flush is quiet
        return EXIT_OK
    except (TactileError, OSError, ValueError) as e:
        if getattr(args, "debug", False):
            raise
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return exit_code(e)


class Parser(argparse.ArgumentParser):
    """``argparse`` with the project's conventions: a bad argument is one line on stderr and
    exit code 1 (argparse's own is 2, which the commands keep for the device), and the
    description's ``literal`` markup is shown as plain text."""

    def __init__(self, *args, **kwargs) -> None:
        if kwargs.get("description"):
            kwargs["description"] = kwargs["description"].replace("``", "")
        super().__init__(*args, **kwargs)

    def error(self, message: str):  # type: ignore[override]
        print(f"{self.prog}: error: {message} (see --help)", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer in ``low .. high`` (no upper bound when ``high`` is None)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low or (high is not None and value > high):
            span = f">= {low}" if high is None else f"in {low}..{high}"
            raise argparse.ArgumentTypeError(f"{value} must be {span}")
        return value

    return parse


def float_in(low: float, high: float = math.inf, low_open: bool = True,
             high_open: bool = False) -> Callable[[str], float]:
    """An argparse type: a number between ``low`` and ``high``, each end open or closed. NaN
    never passes; ``inf`` passes only when ``high`` is infinite (``--seconds inf``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        ok = not math.isnan(value) and (value > low if low_open else value >= low) and (
            value < high if high_open else value <= high)
        if not ok:
            lo = f"> {low}" if low_open else f">= {low}"
            hi = "" if math.isinf(high) else (f" and < {high}" if high_open else f" and <= {high}")
            raise argparse.ArgumentTypeError(f"{text} must be {lo}{hi}")
        return value

    return parse


# What each optional extra brings: a command that needs one says so in one line.
_EXTRA_OF = {"torch": "train", "onnx": "train", "onnxscript": "train", "tqdm": "train",
             "matplotlib": "train"}


def _with_extra(module: str, prog: str) -> Callable[[], int]:
    """An entry point that imports ``module`` only when run, so that a command whose
    dependencies are not installed (the board installs the runtime's only) says which extra
    it needs instead of showing an import traceback."""

    def main() -> int:
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as e:
            top = (e.name or "").split(".")[0]
            if top not in _EXTRA_OF:
                raise
            extra = _EXTRA_OF[top]
            print(f"{prog}: error: needs the [{extra}] extra (no module named {top!r}): "
                  f"pip install 'tactile-pen[{extra}]'", file=sys.stderr)
            return EXIT_USAGE
        return mod.main()

    return main


class _Stopped(BaseException):
    """SIGINT or SIGTERM before a long-running command installed its own handlers."""


_starting = [False]  # True from a guarded entry point's start until the command's started()


def started() -> None:
    """Say that the command is about to install its own SIGINT/SIGTERM handlers: from here on
    the start-up guard (:func:`_guarded_start`) no longer stops the process. A signal that
    still reaches it (after a library call put the previous handlers back, while the summary
    is printed) is ignored: the command has already stopped reading and is finishing."""
    _starting[0] = False


def _guarded_start(module: str, prog: str) -> Callable[[], int]:
    """An entry point for the long-running commands (``tactile-run``, ``tactile-record``): a
    SIGINT or SIGTERM that arrives while the command starts (importing numpy and
    onnxruntime, loading the model: about half a second) stops it with one line and exit 0,
    as one later does, instead of a ``KeyboardInterrupt`` traceback (SIGINT) or an exit
    without a word (SIGTERM). The command calls :func:`started` and replaces these handlers
    with its own (which finish the take or print the summary) before it reads any data."""

    def main() -> int:
        def stop(signum, frame):
            if _starting[0]:
                raise _Stopped(signal.Signals(signum).name)

        try:
            _starting[0] = True
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, stop)
            return importlib.import_module(module).main()
        except _Stopped as e:
            print(f"{prog}: stopped by {e}", file=sys.stderr)
            return EXIT_OK

    return main


run_main = _guarded_start("tactile.runtime.cli", "tactile-run")
record_main = _guarded_start("tactile.device.recorder", "tactile-record")
train_main = _with_extra("tactile.training.train", "tactile-train")
eval_main = _with_extra("tactile.training.evaluate", "tactile-eval")
export_main = _with_extra("tactile.export.cli", "tactile-export")


def add_debug(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--debug", action="store_true", help="show the full traceback on errors")


__all__ = ["ConfigError", "Parser", "run", "add_debug", "exit_code", "float_in", "int_in",
           "EXIT_DEVICE", "EXIT_USAGE"]
