"""``tactile-data DATA [--json]``: what a dataset folder holds, per class and per user.

    tactile-data data/sim                 # a table: takes, users, minutes, windows, gaps
    tactile-data data/sim --json          # the same figures as one JSON object

Windows are counted as training cuts them (inside gap-free segments) at the training defaults'
window and hop, or at ``--window``/``--hop``. Needs numpy only (no torch).
"""

from __future__ import annotations

import argparse
import json
import sys

from tactile.cli import Parser, add_debug, command, holding_signals, int_in, path_given, run


def build_parser() -> argparse.ArgumentParser:
    from tactile.device.recordings.summary import HOP, WINDOW  # training's defaults

    p = Parser(prog="tactile-data", description="Print what a dataset folder holds: classes, "
               "users, takes, minutes, windows, gaps, channels and rate.")
    p.add_argument("data", type=path_given, help="dataset folder (takes: .csv + .json)")
    p.add_argument("--window", type=int_in(4), default=WINDOW,
                   help=f"window length in samples, >= 4 as training takes (default {WINDOW})")
    p.add_argument("--hop", type=int_in(1), default=HOP,
                   help=f"samples between windows (default {HOP}, as training)")
    p.add_argument("--json", action="store_true", help="the figures as one JSON object")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    with holding_signals():
        from tactile.device.recordings.reader import load_dataset
        from tactile.device.recordings.summary import summarise, text

    s = summarise(load_dataset(args.data), args.window, args.hop)
    print(json.dumps(s) if args.json else text(s, args.data))
    return 0


@command("tactile-data", interruptible=True)
def main(argv: list[str] | None = None) -> int:
    return run("tactile-data", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
