"""``tactile-import-biotac``: BioTac BOLT recordings (HDF5) as takes, one per trial.

    tactile-import-biotac PATH/cork.h5 PATH/metal_bar.h5 ... --out data/biotac

Needs h5py (the ``[biotac]`` extra).
"""

from __future__ import annotations

import argparse
import sys

from tactile.cli import Parser, add_debug, command, holding_signals, path_given, run


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-import-biotac",
               description="Import BioTac BOLT recordings (HDF5): one take per trial.")
    p.add_argument("files", type=path_given, nargs="+", metavar="FILE.h5",
                   help="one HDF5 file per object (e.g. cork.h5), one group per trial")
    p.add_argument("--out", type=path_given, required=True, help="dataset folder to write")
    p.add_argument("--force", action="store_true", help="replace takes of the same names")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    with holding_signals():
        from tactile.device.recordings.biotac import import_biotac

    # each take's path as it is written whole: a stop later leaves those, and says so
    import_biotac(args.files, args.out, args.force, written=lambda p: print(p, flush=True))
    return 0


@command("tactile-import-biotac", interruptible=True, files=True, terminable=True)
def main(argv: list[str] | None = None) -> int:
    return run("tactile-import-biotac", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
