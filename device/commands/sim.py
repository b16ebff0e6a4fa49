"""``tactile-sim``: the simulated pen as a pseudo-terminal, or a whole synthetic dataset.

    tactile-sim --pty --texture paper --seed 3        # prints /dev/pts/N, then streams
    tactile-sim --dataset data/sim --takes 20         # 20 takes x 7 textures, as fast as it can

Within Python, the same pen is ``serial.serial_for_url("sim://?texture=paper&seed=3")`` or
``tactile.device.sim.PenSimulator``.
"""

from __future__ import annotations

import argparse
import sys
import time

from tactile.cli import (
    Parser,
    add_debug,
    command,
    float_in,
    holding_signals,
    int_in,
    path_given,
    run,
)


def build_parser() -> argparse.ArgumentParser:
    from tactile.device.sim.textures import TEXTURES  # the classes, named in the help

    p = Parser(prog="tactile-sim", description=__doc__.split("\n\n")[0])
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--pty", action="store_true", help="serve the pen on a pseudo-terminal")
    mode.add_argument("--dataset", type=path_given, metavar="OUT", help="write a synthetic dataset")
    p.add_argument("--takes", type=int_in(1), default=None,
                   help="dataset: takes (simulated users) per texture (default 10)")
    p.add_argument("--textures", default=None,
                   help=f"dataset: comma-separated subset of: {', '.join(TEXTURES)} (default all)")
    p.add_argument("--seconds", type=float_in(0.0), default=None,
                   help="seconds per take (dataset, default 60) or of streaming (pty, default: "
                   "until stopped)")
    p.add_argument("--seed", type=int_in(0), default=0, help="base seed (default 0)")
    p.add_argument("--rate", type=float_in(10.0, 10_000.0, low_open=False), default=100.0,
                   help="sample rate, Hz (default 100)")
    p.add_argument("--first-take", type=int_in(0), default=None,
                   help="dataset: index of the first simulated user (default 0)")
    p.add_argument("--texture", default=None, help="pty: the texture (default paper)")
    p.add_argument("--link", default=None, metavar="OPTIONS",
                   help="pty: more link options as for sim://, e.g. 'garbage=0.01&stall=5:1'")
    p.add_argument("--speed", type=float_in(0.0), default=None,
                   help="pty: speed, x real time (default 1)")
    p.add_argument("--force", action="store_true",
                   help="dataset: replace takes of the same names in the --dataset folder")
    add_debug(p)
    return p


# the options of one mode, with their defaults: given in the other mode they are refused (a
# dataset asked for with --texture desk would be all textures, not the desk)
DATASET_ONLY = {"takes": 10, "textures": None, "first_take": 0}  # textures: all
PTY_ONLY = {"texture": "paper", "link": "", "speed": 1.0}


def _main(args: argparse.Namespace) -> int:
    with holding_signals():
        from tactile.device.sim.dataset import make_dataset
        from tactile.device.sim.pty_server import serve_pty
        from tactile.device.sim.simlink import LinkConfig
        from tactile.device.sim.textures import TEXTURES

    # the parser leaves a mode's own options None when not given: their defaults
    for key, default in {**DATASET_ONLY, **PTY_ONLY}.items():
        if getattr(args, key) is None:
            setattr(args, key, default)
    if args.textures is None:
        args.textures = ",".join(TEXTURES)
    if args.dataset is not None:
        textures = tuple(t.strip() for t in args.textures.split(",") if t.strip())
        t0 = time.perf_counter()
        # each take's path as it is written whole (a stop later leaves those), as the importers
        paths = make_dataset(args.dataset, args.takes, textures, args.seconds or 60.0,
                             args.seed, args.rate, args.first_take, args.force,
                             written=lambda p: print(p, flush=True))
        print(f"tactile-sim: {len(paths)} take{'' if len(paths) == 1 else 's'} in {args.dataset} "
              f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
        return 0
    serve_pty(LinkConfig.from_query(link_query(args)))
    return 0


OWN = ("texture", "seed", "rate", "speed", "seconds")  # the link keys with an option


def link_query(args: argparse.Namespace) -> str:
    """The ``sim://`` query of ``--pty``'s options and ``--link`` (a ``--link`` key that has an
    option of its own is refused: one of the two would be ignored)."""
    from urllib.parse import parse_qsl, urlencode

    from tactile.errors import ConfigError

    # encoded: --seconds 1e20 is 1e+20, and a + in a query is a space
    query = urlencode([(k, getattr(args, k)) for k in OWN
                       if k != "seconds" or args.seconds])  # no --seconds: until stopped
    if args.link:
        given = next((k for k, _ in parse_qsl(args.link, keep_blank_values=True) if k in OWN),
                     None)
        if given is not None:
            raise ConfigError(f"--link {given}=...: give --{given} instead (an option of its "
                              "own)")
        query += "&" + args.link
    return query


@command("tactile-sim", interruptible=True, files=True, terminable=True)
def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    other, mode = (PTY_ONLY, "--dataset") if args.dataset is not None else (
        {**DATASET_ONLY, "force": False}, "--pty")
    for key in other:
        if getattr(args, key) is not None and getattr(args, key) is not False:
            p.error(f"--{key.replace('_', '-')} is not an option of {mode}")
    return run("tactile-sim", _main, args)


if __name__ == "__main__":
    sys.exit(main())
