"""``tactile-export RUN/ -o model.onnx [--int8] [--data DATA]``: a run's checkpoint to one file.

Builds the graph (preprocessing + model + state), measures parity against PyTorch on the run's
test windows (``--data``; else a simulated pen, else random windows), refuses to write a file
that fails it, and writes the contract into the file's metadata. ``--int8`` writes an
onnxruntime dynamic-int8 file instead and reports its size, latency and accuracy against the
float32 one.
"""

from __future__ import annotations

import argparse
import sys

from tactile.cli import Parser, add_debug, command, holding_signals, int_in, path_given, run


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-export", description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=path_given, help="run folder written by tactile-train")
    p.add_argument("-o", "--out", type=path_given, required=True, help="ONNX file to write")
    p.add_argument("--data", type=path_given, help="dataset folder holding the run's test takes")
    p.add_argument("--int8", action="store_true",
                   help="write an onnxruntime dynamic-int8 model (default: float32)")
    p.add_argument("--windows", type=int_in(1), default=256,
                   help="at most this many windows of the data for the parity check "
                   "(default 256); a model that carries its state is also checked along "
                   "simulated runs of windows when no run of the data is long enough")
    add_debug(p)
    return p


def _export(args: argparse.Namespace) -> int:
    with holding_signals():
        import torch

        from tactile.export.exporter import export_run
        from tactile.training.checkpoint import RESUME

    torch.set_num_threads(1)  # one core's figures; also avoids contention on a small board
    if (args.run / RESUME).is_file():  # the run was stopped: its model is not the finished one
        print(f"tactile-export: warning: {args.run}: its training was interrupted ({RESUME} is "
              f"there): the file gets the best model so far; tactile-train --resume "
              f"{args.run} finishes it", file=sys.stderr, flush=True)
    r = export_run(args.run, args.out, args.data, args.int8, args.windows)
    print(f"wrote {args.out}: {r['bytes'] / 1e3:.1f} kB; export took {r['seconds']:.1f} s "
          f"(graph {r['build_s']:.1f} s)")
    return 0


@command("tactile-export", interruptible=True, files=True)
def main(argv: list[str] | None = None) -> int:
    return run("tactile-export", _export, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
