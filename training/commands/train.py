"""Train a classifier on a dataset folder and write an evaluated run: tactile-train DATA --out RUN.

The run's folder and the steps are those of :func:`tactile.training.train.train`; ``--resume
RUN`` continues a run that Ctrl-C (exit 130) or SIGTERM (143) stopped, with its own settings.
Under ``torchrun ... -m tactile.training.commands.train`` the same command trains data-parallel.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import tempfile
from pathlib import Path

from tactile.cli import (
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    Parser,
    Terminated,
    add_debug,
    command,
    holding_signals,
    path_given,
    run,
)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-train", description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=path_given, nargs="?",
                   help="dataset folder (takes: .csv + .json); with --resume, default: the "
                        "run's own")
    p.add_argument("--out", type=path_given, help="run folder to write (must not hold a run)")
    p.add_argument("--config", type=path_given, help="TOML file of settings (docs/training.md, "
                   "'Data' and 'Model'; all of them: TrainConfig in training/config.py)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting, e.g. --set hidden=32 --set emd_channels=accel_z")
    p.add_argument("--resume", type=path_given, metavar="RUN",
                   help="continue the run that Ctrl-C or SIGTERM stopped, with its own "
                   "settings")
    p.add_argument("--force", action="store_true", help="overwrite the run in --out")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_debug(p)
    return p


def _settings(args: argparse.Namespace):
    """(config, dataset folder, run folder, resume state or None) of the command line; the
    run folder is checked first (a run in it is refused unless ``--force``)."""
    with holding_signals():
        from tactile.errors import ConfigError
        from tactile.training.checkpoint import load_resume
        from tactile.training.config import TrainConfig
        from tactile.training.overrides import parse_sets

    if args.resume is not None:
        if args.set or args.config or args.force:
            raise ConfigError("--resume continues a run with its own settings: drop "
                              "--set/--config/--force")
        if args.out is not None and args.out.resolve() != args.resume.resolve():
            raise ConfigError(f"--resume writes into its run folder {args.resume}: drop --out")
        resume = load_resume(args.resume)
        data = args.data if args.data is not None else Path(resume["data"])
        if args.data is None and not data.is_dir():
            raise ConfigError(f"{data}: the run's dataset is not there (moved?): give it, "
                              f"tactile-train DATA --resume {args.resume}")
        return TrainConfig.from_dict(resume["config"]), data, args.resume, resume["state"]
    if args.data is None or args.out is None:
        raise ConfigError("give DATA and --out RUN (or --resume RUN)")
    cfg = TrainConfig.from_toml(args.config) if args.config else TrainConfig()
    cfg = parse_sets(args.set, cfg)
    out = args.out
    _check_out(out)
    if out.exists() and args.data.exists() and out.resolve() == args.data.resolve():
        raise ConfigError(f"--out {out}: the dataset folder itself: the run's files would lie "
                          "among the takes; choose another folder")
    if not args.force:
        _refuse_a_run(out)
    # with --force the old run's files stay until the new run writes its own (a finished run
    # removes resume.pt): a forced run that fails or stops before its first epoch leaves the
    # old run as it was, resumable
    return cfg, args.data, out, None


def _check_out(out: Path) -> None:
    """Refuse, before any work, an --out that is a file or a path through one (whether the
    folder can be written is tried when the training takes it: :func:`_held`)."""
    from tactile.errors import ConfigError

    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: a file, not a folder")
    base = out  # the nearest folder that exists
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        raise ConfigError(f"--out {out}: {base} is a file, not a folder")


@contextlib.contextmanager
def _held(out: Path, option: str, force: bool):
    """The run folder ``out`` (given as ``option``) made, tried and held while training writes
    it, before any training: a folder that cannot be written is refused (tried, not asked:
    ``os.access`` says yes to root, and on /proc or a read-only mount), and so is a second
    ``tactile-train`` into it at the same time (both found no run there, and the two runs'
    files would mix), and a run that another finished meanwhile, as any run there is
    (:func:`_refuse_a_run`) unless ``force``. The hold is an advisory lock on the folder, which
    ends with the process however it ends; a file system without locks (NFS without a lock
    daemon, some FUSE mounts) or Windows holds nothing. Folders made here and left empty are
    removed again. In a torchrun job rank 0 does all of it."""
    if os.environ.get("RANK", "0") != "0":
        yield
        return
    from tactile.errors import ConfigError

    missing, base = [], out  # the folders to make, deepest first
    while not base.exists() and base != base.parent:
        missing.append(base)
        base = base.parent
    made = []
    fd = None
    try:
        try:
            for d in reversed(missing):
                d.mkdir(exist_ok=True)
                made.append(d)
            with tempfile.TemporaryFile(dir=out):
                pass
        except OSError as e:
            raise ConfigError(f"{option} {out}: cannot be written ({e.strerror or e})") from None
        try:
            fd = _lock(out)
        except BlockingIOError:
            wait = "wait for it to end" if option == "--resume" else "choose another --out"
            raise ConfigError(f"{option} {out}: another tactile-train is writing into it now: "
                              f"{wait}") from None
        if option == "--out" and not force:
            _refuse_a_run(out)
        yield
    finally:
        for d in reversed(made):  # before the lock ends: no other training holds them yet
            try:
                d.rmdir()  # only when nothing was written
            except OSError:
                break
        if fd is not None:
            os.close(fd)


def _lock(folder: Path) -> int | None:
    """An open descriptor of ``folder`` holding its advisory lock, or None where nothing can be
    held (Windows, a file system without locks); :class:`BlockingIOError` when another process
    holds it."""
    try:
        import fcntl
    except ImportError:
        return None
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        os.close(fd)
        if isinstance(e, BlockingIOError):
            raise
        return None
    return fd


def _refuse_a_run(out: Path) -> None:
    """A :class:`ConfigError` when ``out`` holds a run (without ``--force``)."""
    from tactile.errors import ConfigError
    from tactile.training.checkpoint import RESUME, RUN_FILES

    held = [f for f in RUN_FILES if (out / f).exists()]
    if held:
        more = (f", or --resume {out} to continue it" if (out / RESUME).exists()
                else " (it finished: nothing to resume)")
        raise ConfigError(f"{out}: holds a run already ({held[0]}): choose another --out "
                          f"or add --force to overwrite it{more}")


def _train(args: argparse.Namespace) -> int:
    with holding_signals():
        from tactile.training.evaluate import per_take_line, shifted_line, table
        from tactile.training.train import train

    cfg, data, out, resume = _settings(args)
    try:
        with _held(out, "--resume" if args.resume is not None else "--out", args.force):
            m = train(data, out, cfg, progress=not args.quiet, resume=resume)
    except KeyboardInterrupt as e:  # before the first epoch (loading, EMD features)
        term = isinstance(e, Terminated)
        print(f"tactile-train: {'terminated (SIGTERM)' if term else 'interrupted'} before "
              "training started: nothing saved", file=sys.stderr)
        return EXIT_TERMINATED if term else EXIT_INTERRUPTED
    if m.get("interrupted"):
        return EXIT_TERMINATED if m.get("stopped_by") == "SIGTERM" else EXIT_INTERRUPTED
    if "accuracy" not in m:  # not rank 0 of a torchrun job: rank 0 prints
        return 0
    # the run is saved: its lines, exit 0, whatever signal comes now
    was = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        print(table(m, tuple(m["classes"]), f"test split ({m['split']})"))
        print(per_take_line(m))
        print(shifted_line(m["shifted"]))
        cpu = f", {m['train_cpu_seconds']} s of CPU" if "train_cpu_seconds" in m else ""
        print(f"trained in {m['train_seconds']} s of wall time{cpu}; run in {out}")
    finally:
        for s, handler in was.items():
            signal.signal(s, handler)
    return 0


@command("tactile-train", interruptible=True, files=True, terminable=True)
def main(argv: list[str] | None = None) -> int:
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        # torchrun's agent ends the workers with SIGTERM: Python's default, which also ends a
        # worker that waits in C for a peer that is gone (a handler would wait with it)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    return run("tactile-train", _train, build_parser().parse_args(argv))


if __name__ == "__main__":  # torchrun ... -m tactile.training.commands.train
    sys.exit(main())


__all__ = ["build_parser", "main", "EXIT_INTERRUPTED"]
