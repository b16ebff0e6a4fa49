"""Two exported files' time per window at batch 1, as the runtime calls them, side by side.

    python bench/compare_models.py A.onnx B.onnx [--rounds 15]

Both files run with the runtime's options (``session_options(1)``: one thread, sequential, no
spinning, no arena) on the same random window, in alternating rounds of 50 calls (so that a
change in the machine's load reaches both alike); prints the median CPU time of this process
per window of each and B / A. What an option of the model (``wide``, a hidden size, EMD
features) costs on the board: export one run with it and one without, and compare them here.
The two files must take the same inputs.
"""

from __future__ import annotations

import argparse
import sys
import time

import onnxruntime as ort
from batch_mix import alternate, feeds, per_call

from tactile.runtime.model import session_options


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", metavar="A.onnx")
    ap.add_argument("b", metavar="B.onnx")
    ap.add_argument("--rounds", type=int, default=15, help="alternating rounds (default 15)")
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")
    try:
        a, b = (ort.InferenceSession(m, session_options(1), providers=["CPUExecutionProvider"])
                for m in (args.a, args.b))
    except Exception as e:  # noqa: BLE001 - onnxruntime raises its own types: one line
        print(f"compare_models.py: {' '.join(str(e).split())[:200]}", file=sys.stderr)
        return 2
    shapes = [[i.name, i.shape] for i in a.get_inputs()]
    if shapes != [[i.name, i.shape] for i in b.get_inputs()]:
        print(f"compare_models.py: {args.a} and {args.b} take different inputs", file=sys.stderr)
        return 2
    feed = feeds(a, 1)
    for s in (a, b):
        per_call(s, feed, 20)  # warm up
    ta, tb = alternate(args.rounds, lambda: per_call(a, feed, 50, time.process_time),
                       lambda: per_call(b, feed, 50, time.process_time))
    print(f"A {args.a}: {1e3 * ta:.3f} ms a window; B {args.b}: {1e3 * tb:.3f} ms; "
          f"B / A {tb / ta:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
