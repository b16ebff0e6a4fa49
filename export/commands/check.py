"""``tactile-check model.onnx [--run RUN] [--data DATA]``: is this file a model we can deploy?

Validates the contract of any ONNX file (an ONNX model at all, ``onnx.checker``, opset, input
and output names, dtypes, ranks, the dynamic batch axis, every required metadata key) and names
what is wrong in one line (exit code 3). With ``--run`` it re-runs the parity comparison against
the run's PyTorch model (on at most ``--windows`` of ``--data``'s test windows if given, else
simulated or random ones) and prints the table; exit 3 on failure. A file with custom nodes
(EMD, sparse codes) is compared on the portable graph and, where the native kernels run it,
on the kernels too: both must pass. With ``--data`` alone it runs the file, as ``tactile-run``
would (kernels or portable graph, as the ``kernels`` lines say), on all of the data's windows
(the run's test split when the data holds its test takes, recognised by content, else every
take, and it says which) and prints the accuracy beside the one training recorded, saying what
that was measured on.

On a board (no ``[train]`` extra: no onnx, no torch) it checks what the runtime will: loads the
file with onnxruntime, validates the contract and the graph's signature as ``tactile-run`` does,
and runs one window through it; ``--run`` and ``--data`` need the extra.
"""

from __future__ import annotations

import argparse
import sys

from tactile.cli import Parser, add_debug, command, holding_signals, int_in, path_given, run


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-check", description=__doc__.split("\n\n")[0])
    p.add_argument("model", type=path_given, help="ONNX file to check")
    p.add_argument("--run", type=path_given,
                   help="run folder: re-run parity against its PyTorch model")
    p.add_argument("--data", type=path_given, help="dataset folder: windows to check on")
    p.add_argument("--windows", type=int_in(1), default=None,
                   help="--run: compare on at most this many windows (default: 256)")
    p.add_argument("--no-native", action="store_true",
                   help="run the portable EMD/sparse-code graphs, not the C kernels")
    add_debug(p)
    return p


def _check(args: argparse.Namespace) -> int:
    with holding_signals():  # (check_file holds its own heavier imports)
        from tactile.export.check import check_file

    if args.no_native:
        from tactile.runtime import kernels

        kernels.disable()
    check_file(args.model, args.run, args.data, args.windows)
    return 0


@command("tactile-check", interruptible=True)
def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.windows is not None and args.run is None:  # it would be ignored in silence
        parser.error("argument --windows: only with --run (the windows of the parity check)")
    args.windows = 256 if args.windows is None else args.windows
    return run("tactile-check", _check, args)


if __name__ == "__main__":
    sys.exit(main())
