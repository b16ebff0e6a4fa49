"""What every command line shares: one-line errors, exit codes, ``--debug``."""

from __future__ import annotations

import argparse
import contextlib
import errno
import functools
import math
import os
import re
import signal
import sys
import threading
import traceback
from collections.abc import Callable
from pathlib import Path

from tactile.errors import (
    ConfigError,
    DeviceError,
    ModelContractError,
    OutputError,
    TactileError,
)

# Exit codes, documented in README.md: 0 ok, 1 bad input, 2 device/port, 3 model contract, 4 an
# output that cannot be written (a full disk: stdout, an exported model, a run, a picture).
EXIT_OK, EXIT_USAGE, EXIT_DEVICE, EXIT_CONTRACT = 0, 1, 2, 3
EXIT_OUTPUT = 4  # an output cannot be written (a full disk): a service may restart
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143  # the shell's codes for an end by SIGINT, SIGTERM
FULL_DISK = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)  # errnos of an output with no room: exit 4
MAX_THREADS = 1024  # a command's or a setting's threads: far above any machine's use


def exit_code(err: BaseException) -> int:
    if isinstance(err, ModelContractError):
        return EXIT_CONTRACT
    if isinstance(err, DeviceError):
        return EXIT_DEVICE
    try:
        import serial

        if isinstance(err, serial.SerialException):  # (an OSError, with the port's errno)
            return EXIT_DEVICE
    except ImportError:  # pragma: no cover
        pass
    if isinstance(err, OutputError) or (isinstance(err, OSError) and err.errno in FULL_DISK):
        return EXIT_OUTPUT  # a full disk: freeing space may be all it takes
    return EXIT_USAGE


def run(prog: str, body: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Run ``body(args)``; a user's mistake becomes one line on stderr and a non-zero exit."""
    try:
        return body(args)
    except BrokenPipeError:  # the reader of stdout went away (`| head`): stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so that the interpreter's final flush is quiet
        return EXIT_OK
    except (TactileError, OSError, ValueError, MemoryError, RuntimeError) as e:
        msg = _out_of_memory(e) if isinstance(e, (MemoryError, RuntimeError)) else (
            str(e).splitlines()[0] if str(e) else type(e).__name__)
        code = exit_code(e)
        if isinstance(e, OSError) and e.filename is None and _stdout_failed():
            msg, code = f"stdout: cannot write ({e.strerror or e})", EXIT_OUTPUT
        if msg is None:  # a RuntimeError that is not an allocation: a defect, shown as one
            raise
        if getattr(args, "debug", False):  # the traceback, then the same line and exit code
            traceback.print_exc()
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return code


def _stdout_failed() -> bool:
    """Whether a write to the command's stdout (:class:`_Stdout`) failed."""
    out = sys.stdout
    while isinstance(out, _ReaderMayGo):
        out = out._stream
    return isinstance(out, _Stdout) and out.failed


def _out_of_memory(e: BaseException) -> str | None:
    """The line for an allocation that failed (numpy's MemoryError, torch's "can't allocate
    memory" RuntimeError: a setting such as hidden=1000000 asks for more than the machine
    has), or None for any other error."""
    text = str(e)
    if isinstance(e, MemoryError) or "can't allocate memory" in text:
        asked = re.search(r"allocate (\d+) bytes", text) or re.search(r"allocate ([\d.]+ \w+)",
                                                                     text)
        size = (f"{int(asked.group(1)) / 2**30:.1f} GiB" if asked.group(1).isdigit()
                else asked.group(1)) if asked else None
        return "out of memory" + (f" (an allocation of {size})" if size else "") + \
            ": smaller settings (hidden, batch_size, window) or a smaller dataset"
    return None


class Parser(argparse.ArgumentParser):
    """``argparse`` with the project's conventions: a bad argument is one line on stderr and
    exit code 1 (argparse's own is 2, which the commands keep for the device), and the
    description's ``literal`` markup is shown as plain text."""

    def __init__(self, *args, **kwargs) -> None:
        if kwargs.get("description"):
            kwargs["description"] = kwargs["description"].replace("``", "")
        super().__init__(*args, **kwargs)
        from tactile import __version__

        self.add_argument("--version", action="version", version=f"%(prog)s {__version__}")

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        self._given = list(sys.argv[1:] if args is None else args)  # for error()'s hint
        return super().parse_known_args(args, namespace)

    def error(self, message: str):  # type: ignore[override]
        hint = ""
        m = re.fullmatch(r"argument ([^:]*/)?(--[\w-]+): expected one argument", message)
        given = getattr(self, "_given", [])
        if m and m.group(2) in given:  # ``--smooth -1s``: argparse took -1s for an option
            k = given.index(m.group(2))
            after = given[k + 1].split("=")[0] if k + 1 < len(given) else ""
            if after.startswith("-") and not after.startswith("--") \
                    and after not in self._option_string_actions:
                hint = (f"; a value that starts with '-' goes after '=': "
                        f"{m.group(2)}={given[k + 1]}")
        print(f"{self.prog}: error: {message}{hint} (see --help)", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def smooth_given(text: str) -> str:
    """An argparse type: a label stream's ``--smooth`` (``N`` windows, ``Ts``, ``ma:N`` or
    ``ema:T``), checked here so that a bad value is argparse's one line naming the option."""
    from tactile.postprocess.smoothing import parse_smooth_option

    try:
        parse_smooth_option(text)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


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


def path_given(text: str) -> Path:
    """An argparse type: a path that is not empty (``Path("")`` is the current folder; a
    name of spaces is a name)."""
    if text == "":
        raise argparse.ArgumentTypeError("an empty path")
    return Path(text)


_ADDRESS = "expected HOST:PORT or PORT (0-65535), e.g. 127.0.0.1:8000"


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``[v6]:PORT`` or ``PORT`` (then host 127.0.0.1) -> (host, port); port 0
    picks a free one. :class:`ConfigError` naming the value otherwise."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]") if sep else "127.0.0.1"
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not host or not 0 <= number <= 65535:
        raise ConfigError(f"--serve {text!r}: {_ADDRESS}")
    return host, number


def _address(text: str) -> str:
    """``--serve``'s argparse type: ``text`` when :func:`parse_address` reads it (a bad value
    is argparse's one line, before the command loads anything)."""
    try:
        parse_address(text)
    except ConfigError:
        raise argparse.ArgumentTypeError(f"{text!r}: {_ADDRESS}") from None
    return text


# What each optional extra brings: a command that needs one says so in one line.
_EXTRA_OF = {"torch": "train", "onnx": "train", "onnxscript": "train", "tqdm": "train",
             "matplotlib": "train", "sklearn": "train", "h5py": "biotac"}

_start = {"guarded": False, "signal": None}  # see command(guarded=True) and started()


def started() -> str | None:
    """Called by a long-running command just before it installs its own SIGINT/SIGTERM
    handlers. Returns the name of a signal that arrived while it was starting under
    ``command(guarded=True)`` (the command then stops at once, cleanly), else None. From here
    on the start-up handlers ignore signals: one that still reaches them (after a library call
    put the previous handlers back, while the summary is printed) finds the command finishing
    anyway."""
    _start["guarded"] = False
    return _start["signal"]


def _die_by(signum: int) -> None:
    """End the process at once by signal ``signum``: a second signal while the first is only
    noted (:func:`_guard_start`, :func:`holding_signals`)."""
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)


def _guard_start() -> None:
    """Install the start-up handlers of ``command(guarded=True)``: a SIGINT or SIGTERM that
    arrives while the command starts (importing numpy and onnxruntime, loading the model:
    0.1-0.2 s on the development VM) is remembered, and the command stops cleanly as soon as
    it has started (:func:`started`), instead of dying with a ``KeyboardInterrupt`` traceback
    (SIGINT) or without a word (SIGTERM). The handlers only take note: an exception raised
    from a handler while a C extension initialises becomes onnxruntime's ``ImportError:
    initialization failed``. A second signal while starting ends the process at once, by that
    signal (a start stuck on a slow disk can still be interrupted)."""

    def note(signum, frame):
        if not _start["guarded"]:
            return
        if _start["signal"] is None:
            _start["signal"] = signal.Signals(signum).name
        else:  # a second one: the start is stuck, or the user insists
            _die_by(signum)

    _start["guarded"], _start["signal"] = True, None  # a signal of an earlier call is past
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, note)


@contextlib.contextmanager
def holding_signals():
    """Ctrl-C (and SIGTERM where the command takes it as Ctrl-C) held back while the block
    runs, then raised where the block ends: around imports, and around steps that must not
    stop half-way (moving a take aside and back, :func:`tactile.device.recordings.take.
    whole_take`). An import stopped midway can leave a library half-built, so that a later
    import fails with another error (numpy's ``RecursionError`` under onnx, seen on
    ``tactile-export``) instead of the ``KeyboardInterrupt`` that ends the command with its
    one line. A second signal while held ends the process at once, by that signal (an import
    stuck on a slow disk can still be stopped); an error raised in the block wins over a held
    signal. The handlers are swapped
    with the signals blocked, so that none runs between two swaps. Off the main thread, and
    for a signal whose handler is a caller's own, the block runs as it is."""
    held = {}
    if threading.current_thread() is threading.main_thread():
        for sig, ours in ((signal.SIGINT, signal.default_int_handler),
                          (signal.SIGTERM, _terminate)):
            if signal.getsignal(sig) is ours:
                held[sig] = ours
    got: list[int] = []

    def note(signum, frame):
        if got:  # a second one: the import is stuck, or the user insists
            _die_by(signum)
        got.append(signum)

    def swap(handlers: dict) -> None:
        mask = (signal.pthread_sigmask(signal.SIG_BLOCK, handlers)
                if handlers and hasattr(signal, "pthread_sigmask") else None)
        try:
            for sig, handler in handlers.items():
                signal.signal(sig, handler)
        finally:
            if mask is not None:  # (a signal that came meanwhile reaches the new handler)
                signal.pthread_sigmask(signal.SIG_SETMASK, mask)

    swap(dict.fromkeys(held, note))
    try:
        yield
    finally:
        swap(held)
    if got:
        held[got[0]](got[0], None)  # raises KeyboardInterrupt, or Terminated


_null_out = None  # the stream that stands in for a closed stdout or stderr


def _fill_closed_streams() -> None:
    """A command started with stdin, stdout or stderr closed (``>&-``, ``2>&-``, a service
    manager's choice) gets the null device there: otherwise the next file it opens (a take
    being recorded, an exported model) takes the free descriptor 1 or 2 and any write to
    stdout or stderr, onnxruntime's and PyTorch's own among them, lands in that file, and
    Python, which left ``sys.stdout`` or ``sys.stderr`` None, would end the first ``print``
    with a traceback or send stderr's lines to stdout. The lines of a closed stream are
    dropped; the command goes on. ``sys.stdout`` or ``sys.stderr`` None (the process started
    so; its descriptor may since hold another file) writes to the null device, whatever the
    descriptor holds; the command's ``finally`` puts None back."""
    global _null_out
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
            continue
        except OSError:
            pass
        null = os.open(os.devnull, os.O_RDWR)  # the lowest free descriptor: fd itself
        if null != fd:
            os.dup2(null, fd)
            os.close(null)
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:
            if _null_out is None:
                _null_out = open(os.devnull, "w", encoding="utf-8",  # kept for the process
                                 errors="backslashreplace")  # (as Python's own stderr)
            setattr(sys, name, _null_out)


def _paths_as_they_are() -> None:
    """stdout writes a path's bytes that are no UTF-8 as they are (Python reads them into
    lone surrogates): with a strict stdout, the default in a UTF-8 locale, printing such a
    path raised after the work had begun (one of two simulated takes written, exit 1). A
    stream that already forgives is left alone (a test's capture, a pipe in the C locale)."""
    out = sys.stdout
    if getattr(out, "errors", None) == "strict" and hasattr(out, "reconfigure"):
        try:
            out.reconfigure(errors="surrogateescape")
        except (ValueError, OSError):  # a closed or detached stream: as it was
            pass


class _ReaderMayGo:
    """stdout of a command whose work is its files (training, an export, an import, a
    recording), and every command's stderr: when the reader of the stream goes away (``2>&1 |
    head``), the rest of the lines go to the null device and the work goes on, instead of the
    broken pipe ending it half-done with exit 0. On stderr (``any_final``) a write that fails for
    good does the same (a full disk, an I/O error: ``2>/dev/full``): diagnostics that cannot
    be written are dropped, as on a closed stderr, never the command's work or its exit code.
    The process's own descriptor (1 or 2) is pointed at the null device; a caller's stream is
    replaced in the wrapper, its descriptor left alone."""

    # the errors after which a stream takes no more lines (a full disk, an I/O error, a quota,
    # a file too large); not EAGAIN and the like, after which it may
    FINAL = frozenset({errno.EPIPE, errno.ENOSPC, errno.EIO, errno.EDQUOT, errno.EFBIG})

    def __init__(self, stream, any_final: bool = False) -> None:
        self._stream, self._any_final = stream, any_final

    def _gone(self, e: OSError) -> bool:
        return isinstance(e, BrokenPipeError) or (self._any_final and e.errno in self.FINAL)

    def _drop_the_rest(self) -> None:
        try:
            fd = self._stream.fileno()
        except (OSError, ValueError):
            fd = None
        if fd not in (1, 2):  # a caller's own stream: replaced here, its descriptor left alone
            self._stream = open(os.devnull, "w", encoding="utf-8")
            return
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, fd)
        os.close(devnull)

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except OSError as e:
            if not self._gone(e):
                raise
            self._drop_the_rest()
            return self._stream.write(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except OSError as e:
            if not self._gone(e):
                raise
            self._drop_the_rest()
            self._stream.flush()

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


class _Stdout:
    """A command's stdout, noting a write that fails (a full disk) so that its one line can say
    that it was stdout: the OSError from a flush names no file."""

    def __init__(self, stream) -> None:
        self._stream = stream
        self.failed = False

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except OSError as e:
            self.failed = not isinstance(e, BrokenPipeError)
            raise

    def flush(self) -> None:
        try:
            self._stream.flush()
        except OSError as e:
            self.failed = not isinstance(e, BrokenPipeError)
            raise

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


class Terminated(KeyboardInterrupt):
    """SIGTERM in a command that takes it as Ctrl-C (``command(terminable=True)``): raised
    where the command is, so that what a Ctrl-C cleans up (a half-written take) is cleaned up
    after ``timeout``, ``kill`` and a service manager's stop too."""


def _terminate(signum, frame) -> None:
    raise Terminated()


def terminable_here() -> bool:
    """Whether SIGTERM here is a command's own (``command(terminable=True)``), which a
    library function may then take over as Ctrl-C (training saves its run); not in a caller
    that kept Python's default or set a handler of its own."""
    return signal.getsignal(signal.SIGTERM) is _terminate


_local = threading.local()  # .running: the commands running in this thread (a test nests them)


def _running() -> list[str]:
    if not hasattr(_local, "running"):
        _local.running = []
    return _local.running


def prefix(outside: str = "") -> str:
    """``"tactile-x: "`` while the command ``tactile-x`` runs in this thread, else ``outside``:
    for the library's own warning lines, so that they name the command as its errors do."""
    running = _running()
    return f"{running[-1]}: " if running else outside


def _is_the_process(prog: str, main: Callable[..., int]) -> bool:
    """Whether the command is what this process runs: its console script (``sys.argv[0]``
    named ``prog``) or its module run by ``python -m``; not a script that calls ``main()``."""
    if threading.current_thread() is not threading.main_thread():
        return False
    return main.__module__ == "__main__" or bool(sys.argv and Path(sys.argv[0]).name == prog)


def _ignore_ctrl_c_from_now() -> None:
    """SIGINT ignored for the rest of the process, whose command has returned its code: a
    Ctrl-C in the interpreter's teardown (0.1-0.5 s after torch or onnx) would end it by
    SIGINT, no line, as if the finished work had failed. Only SIG_IGN lasts through the
    teardown (Python puts its own handlers back to the default late in it). SIGTERM is left
    as it is: a stuck teardown can still be ended, and torchrun's agent ends its workers so.
    A SIGINT already pending (the work was done before it) is dropped."""
    while True:
        try:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            return
        except KeyboardInterrupt:  # (checked before the handler changes: set it again)
            continue


def command(prog: str, *, guarded: bool = False, interruptible: bool = False,
            files: bool = False, terminable: bool = False
            ) -> Callable[[Callable[..., int]], Callable[..., int]]:
    """Decorate a command's ``main(argv=None)``, the function ``pyproject.toml`` names.

    A command module imports only the standard library and this module at its top; its
    ``main`` imports the library it drives. So a command whose optional dependencies are not
    installed (a board installs the runtime's only) says in one line which extra it needs
    instead of showing an import traceback. ``guarded``: the long-running commands
    (``tactile-run``, ``tactile-record``, ``tactile-monitor``) note a signal that arrives while
    they start (:func:`_guard_start`). ``interruptible``: a Ctrl-C that the command does not
    handle itself (while torch imports, say) ends it with one line and exit 130, the shell's
    code for SIGINT, not a traceback; with ``terminable`` SIGTERM does the same (exit 143) where
    its handler is the default (not in a caller that set its own, nor off the main thread).
    ``files``: the command's work is the files it writes, which a reader of its output that
    goes away does not stop (:class:`_ReaderMayGo`; stderr's reader, or a stderr that cannot
    be written, stops no command). Run as the process's command (its console
    script, or ``python -m`` its module), a command ignores SIGINT once it has returned its
    code (:func:`_ignore_ctrl_c_from_now`)."""

    def wrap(main: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(main)
        def entry(argv: list[str] | None = None) -> int:
            depth = len(_running())
            if guarded:  # the command's signal handlers last as long as the command
                handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
                _guard_start()
            term = None
            if terminable and threading.current_thread() is threading.main_thread() and \
                    signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
                term = signal.signal(signal.SIGTERM, _terminate)
            was = (sys.stdout, sys.stderr)
            if depth == 0 and threading.current_thread() is threading.main_thread():
                _fill_closed_streams()
                _paths_as_they_are()
                sys.stdout = _Stdout(sys.stdout)  # the outermost command's, as a process has
            if files and not isinstance(sys.stdout, _ReaderMayGo):
                sys.stdout = _ReaderMayGo(sys.stdout)
            if not isinstance(sys.stderr, _ReaderMayGo):
                sys.stderr = _ReaderMayGo(sys.stderr, any_final=True)
            try:
                _running().append(prog)
                return main(argv)
            except ModuleNotFoundError as e:
                top = (e.name or "").split(".")[0]
                if top not in _EXTRA_OF:
                    raise
                extra = _EXTRA_OF[top]
                print(f"{prog}: error: needs the [{extra}] extra (no module named {top!r}): "
                      f"pip install 'tactile-pen[{extra}]'", file=sys.stderr)
                return EXIT_USAGE
            except KeyboardInterrupt as e:
                if not interruptible:
                    raise
                if isinstance(e, Terminated):
                    print(f"{prog}: terminated (SIGTERM)", file=sys.stderr)
                    return EXIT_TERMINATED
                print(f"{prog}: interrupted", file=sys.stderr)
                return EXIT_INTERRUPTED
            finally:
                del _running()[depth:]
                if term is not None:
                    signal.signal(signal.SIGTERM, term)
                sys.stdout, sys.stderr = was
                if guarded:  # called in-process (a test, a script): the caller's own again
                    _start["guarded"] = False
                    for s, h in handlers.items():
                        signal.signal(s, h)
                if argv is None and depth == 0 and _is_the_process(prog, main):
                    _ignore_ctrl_c_from_now()

        return entry

    return wrap


def add_debug(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--debug", action="store_true", help="show the full traceback on errors")


BAUD = 115200  # --baud's default
STALL_TIMEOUT = 2.0  # --stall-timeout's default, s


def add_port_options(parser: argparse.ArgumentParser, page: str,
                     until: str = "Ctrl-C or the end of a --replay") -> None:
    """The options of every command that reads a pen live (``tactile-run``,
    ``tactile-monitor``): ``--baud``, ``--seconds``, ``--stall-timeout`` and ``--serve`` (the
    page's contents, ``page``, and what ends the command without ``--seconds``, ``until``, are
    said in their help). ``--baud`` and ``--stall-timeout`` stay None unless given, so that a
    command can tell (``tactile-run --replay`` refuses them): :func:`link_values` gives them
    with their defaults."""
    parser.add_argument("--baud", type=int_in(1),
                        help=f"UART baud rate (default {BAUD})")
    parser.add_argument("--seconds", type=float_in(0.0), default=math.inf,
                        help=f"stop after this long, s of wall time (default: until {until})")
    parser.add_argument("--stall-timeout", type=float_in(0.0),
                        help="report a stall after this many seconds without data (default "
                        f"{STALL_TIMEOUT:g})")
    parser.add_argument("--serve", metavar="HOST:PORT", type=_address,
                        help=f"also serve a live, read-only web page of {page} at "
                        "http://HOST:PORT/ (PORT alone: on 127.0.0.1; port 0: a free one, said "
                        "on stderr)")


def link_values(args: argparse.Namespace) -> tuple[int, float]:
    """``--baud`` and ``--stall-timeout`` of :func:`add_port_options`, their defaults where
    not given."""
    return (BAUD if args.baud is None else args.baud,
            STALL_TIMEOUT if args.stall_timeout is None else args.stall_timeout)


__all__ = ["ConfigError", "Parser", "run", "add_debug", "add_port_options", "exit_code",
           "float_in", "int_in", "link_values", "parse_address", "path_given", "smooth_given",
           "EXIT_DEVICE", "EXIT_USAGE"]
