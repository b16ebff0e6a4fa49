"""``tactile-import-hapmat``: the HapMat stick-IMU recordings as takes.

    tactile-import-hapmat "PATH/HapMat dataset" --out data/hapmat   # the upstream CSV files
    tactile-import-hapmat PATH/hapmat_stick_imu.npz --out data/hapmat  # or the bundled arrays
"""

from __future__ import annotations

import argparse
import sys

from tactile.cli import Parser, add_debug, command, holding_signals, path_given, run


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="tactile-import-hapmat", description="Import the HapMat stick-IMU recordings."
    )
    p.add_argument("source", type=path_given,
                   help="the upstream 'HapMat dataset' folder of CSV files, or the bundled "
                   "hapmat_stick_imu.npz")
    p.add_argument("--out", type=path_given, required=True, help="dataset folder to write")
    p.add_argument("--force", action="store_true", help="replace takes of the same names")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    with holding_signals():
        from tactile.device.recordings.hapmat import import_hapmat

    # each take's path as it is written whole: a stop later leaves those, and says so
    import_hapmat(args.source, args.out, args.force, written=lambda p: print(p, flush=True))
    return 0


@command("tactile-import-hapmat", interruptible=True, files=True, terminable=True)
def main(argv: list[str] | None = None) -> int:
    return run("tactile-import-hapmat", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
