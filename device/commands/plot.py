"""``tactile-plot``: a take's channels over time, or a dataset's minutes per class and user.

    tactile-plot data/sim/paper-user000.csv -o take.png     # channels in units, gaps marked
                                                           # (a declared signal at its rate)
    tactile-plot data/sim --summary -o summary.png         # minutes and gaps per class and user

Needs matplotlib (the ``[train]`` extra).
"""

from __future__ import annotations

import argparse
import sys

from tactile.cli import Parser, add_debug, command, holding_signals, path_given, run


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-plot", description="Plot a take's channels over time (a high-rate "
               "signal the take declares as one trace at its rate), or with --summary a "
               "dataset's minutes and gaps per class and user.")
    p.add_argument("source", type=path_given, help="a take's .csv file, or a dataset folder with "
                   "--summary")
    p.add_argument("-o", "--out", type=path_given, required=True,
                   help="image file to write (.png, .svg, .pdf, ...)")
    p.add_argument("--channels", metavar="PATTERNS", default="",
                   help="only these channels of a take: comma-separated names, shell-style "
                   "patterns or declared signals' names (f0_pac,f1_*); default all")
    p.add_argument("--summary", action="store_true", help="plot a dataset folder's summary")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    with holding_signals():
        from tactile.device.recordings.plot import image_formats, plot_summary, plot_take
        from tactile.device.recordings.reader import read_take, say_mismatch
        from tactile.errors import ConfigError

    if args.out.is_dir() or not args.out.parent.is_dir():
        raise ConfigError(f"-o {args.out}: give an image file in a folder that exists")
    kinds = image_formats()
    if args.out.suffix.lower().lstrip(".") not in kinds:
        raise ConfigError(f"-o {args.out}: name an image file ending in .png, .svg or .pdf "
                          f"(or any of {', '.join(sorted(kinds))})")
    if args.summary:
        if args.channels:
            raise ConfigError("--channels chooses a take's channels; --summary plots a folder's "
                              "minutes and gaps")
        plot_summary(args.source, args.out)
    else:
        if args.source.is_dir():
            raise ConfigError(f"{args.source}: a folder; give a take's .csv, or add --summary")
        take = read_take(args.source)
        say_mismatch(take)  # a finished take that lost rows, as every reader of takes says
        if len(take.seq) == 0:
            raise ConfigError(f"{args.source}: the take holds no samples")
        plot_take(take, args.out, tuple(p for p in args.channels.split(",") if p))
    print(args.out)
    return 0


@command("tactile-plot", interruptible=True)
def main(argv: list[str] | None = None) -> int:
    return run("tactile-plot", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
