"""``tactile-sim``: the simulated pen as a pseudo-terminal, or a whole synthetic dataset.

    tactile-sim --pty --texture paper --seed 3        # prints /dev/pts/N, then streams
    tactile-sim --dataset data/sim --takes 20         # 20 takes x 7 textures, as fast as it can

Within Python, the same pen is ``serial.serial_for_url("sim://?texture=paper&seed=3")`` or
``tactile.device.simulator.PenSimulator``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import signal
import sys
import time
import tty
import zlib
from pathlib import Path

from tactile.cli import Parser, add_debug, float_in, int_in, run
from tactile.device.recording import TakeWriter, dataset_folder, replace_takes
from tactile.device.simlink import LinkConfig, PenLink
from tactile.device.simulator import TEXTURES, PenSimulator
from tactile.errors import ConfigError


def take_seed(base: int, texture: str, take: int) -> int:
    """A stable seed per (texture, take): the same dataset whatever else is generated."""
    return (base * 1_000_003 + zlib.crc32(texture.encode()) * 1009 + take) % 2**31


def make_dataset(
    out: Path,
    takes: int,
    textures: tuple[str, ...] = TEXTURES,
    seconds: float = 60.0,
    seed: int = 0,
    rate_hz: float = 100.0,
    first_take: int = 0,
    force: bool = False,
) -> list[Path]:
    """Write ``takes`` takes per texture; take k of every texture is simulated user k.

    Takes are named ``<texture>-user<k>``: a folder that already holds one of them is refused
    (so that a second run neither overwrites nor duplicates a dataset), unless ``force``, which
    replaces those takes. Other takes in the folder are left alone (``first_take`` adds users).
    """
    for t in textures:
        if t not in TEXTURES:
            raise ConfigError(f"texture {t!r}: must be one of {', '.join(TEXTURES)}")
    if takes < 1 or not seconds > 0:
        raise ConfigError(f"--takes {takes} and --seconds {seconds}: must be >= 1 and > 0")
    out = dataset_folder(out)
    replace_takes(out, [f"{t}-user{k:03d}" for k in range(first_take, first_take + takes)
                        for t in textures], force)
    paths = []
    n = round(seconds * rate_hz)
    for k in range(first_take, first_take + takes):
        for texture in textures:
            s = take_seed(seed, texture, k)
            sim = PenSimulator(texture, seed=s, rate_hz=rate_hz)
            extra = {
                "user": k,
                "simulator": {"texture": texture, "seed": s,
                              "session": dataclasses.asdict(sim.session)},
            }
            name = f"{texture}-user{k:03d}"
            with TakeWriter(out, texture, sim.info, "simulator", name=name, extra=extra) as w:
                for start in range(0, n, 6000):
                    raw = sim.read(min(6000, n - start))
                    w.write(start, round(start * 1e6 / rate_hz), raw)
            paths.append(w.csv_path)
    return paths


def serve_pty(config: LinkConfig, out=sys.stdout) -> None:
    """Stream the pen on a new pseudo-terminal until SIGINT/SIGTERM or ``seconds`` ran out."""
    if config.unplug:
        raise ConfigError("unplug is only simulated on sim:// ports (a pty cannot vanish)")
    if math.isinf(config.speed):
        raise ConfigError("a pty streams in (scaled) real time: give --speed as a number")
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    print(os.ttyname(slave), file=out, flush=True)
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
                    os.write(master, data)
                except BlockingIOError:  # nobody reads: a UART drops, so do we
                    dropped += len(data)
            time.sleep(0.005)
    finally:
        print(f"tactile-sim: {link.injected.samples} samples, {dropped} bytes unread",
              file=sys.stderr)
        os.close(master)
        os.close(slave)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-sim", description=__doc__.split("\n\n")[0])
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--pty", action="store_true", help="serve the pen on a pseudo-terminal")
    mode.add_argument("--dataset", type=Path, metavar="OUT", help="write a synthetic dataset")
    p.add_argument("--takes", type=int_in(1), default=10,
                   help="takes (simulated users) per texture")
    p.add_argument("--textures", default=",".join(TEXTURES),
                   help=f"comma-separated subset of: {', '.join(TEXTURES)}")
    p.add_argument("--seconds", type=float_in(0.0), default=None,
                   help="seconds per take (dataset, default 60) or of streaming (pty, default: "
                   "until stopped)")
    p.add_argument("--seed", type=int_in(0), default=0, help="base seed (default 0)")
    p.add_argument("--rate", type=float_in(10.0, 10_000.0, low_open=False), default=100.0,
                   help="sample rate, Hz (default 100)")
    p.add_argument("--first-take", type=int_in(0), default=0,
                   help="index of the first simulated user")
    p.add_argument("--texture", default="paper", help="texture on the pty (default paper)")
    p.add_argument("--link", default="", metavar="OPTIONS",
                   help="more pty link options as for sim://, e.g. 'garbage=0.01&stall=5:1'")
    p.add_argument("--speed", type=float_in(0.0), default=1.0, help="pty speed, x real time")
    p.add_argument("--force", action="store_true",
                   help="replace takes of the same names in the --dataset folder")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    if args.dataset is not None:
        textures = tuple(t.strip() for t in args.textures.split(",") if t.strip())
        t0 = time.perf_counter()
        paths = make_dataset(args.dataset, args.takes, textures, args.seconds or 60.0,
                             args.seed, args.rate, args.first_take, args.force)
        print(f"tactile-sim: {len(paths)} takes in {args.dataset} "
              f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
        return 0
    query = f"texture={args.texture}&seed={args.seed}&rate={args.rate}&speed={args.speed}"
    if args.seconds:
        query += f"&seconds={args.seconds}"
    if args.link:
        query += "&" + args.link
    serve_pty(LinkConfig.from_query(query))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run("tactile-sim", _main, args)


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["main", "make_dataset", "serve_pty"]
