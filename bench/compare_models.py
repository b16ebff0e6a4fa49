"""Two exported files' time per window at batch 1, as the runtime calls them, side by side.

    python bench/compare_models.py A.onnx B.onnx [--rounds 15]

Both files run with the runtime's options (``session_options(1)``: one thread, sequential, no
spinning, no arena; the native kernel library registered for a file with ``ai.tactile`` nodes,
as ``tactile-run`` registers it, unless ``TACTILE_NATIVE=0``; the path each file takes is
printed) on the same random window, in alternating rounds of 50 calls (so that a
change in the machine's load reaches both alike); prints the median CPU time of this process
per window of each and B / A. What an option of the model (``wide``, a hidden size, EMD
features, an ensemble) costs on the board: export one run with it and one without, and
compare them here. The two files must take the same window ``x``; their other inputs (the
state) may differ in shape, as an ensemble's does, and each gets its own.

Exit status: 0 with the figures printed; 1 for a bad argument, a file onnxruntime cannot load
or two files it cannot compare (one line on stderr).
"""

from __future__ import annotations

import sys
import time

import onnxruntime as ort
from batch_mix import alternate, feeds, per_call

from tactile.cli import Parser
from tactile.runtime import kernels
from tactile.runtime.model import session_options


def main() -> int:
    ap = Parser(prog="compare_models.py", description=__doc__.splitlines()[0])
    ap.add_argument("a", metavar="A.onnx")
    ap.add_argument("b", metavar="B.onnx")
    ap.add_argument("--rounds", type=int, default=15, help="alternating rounds (default 15)")
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")
    try:
        (a, path_a), (b, path_b) = (_session(m) for m in (args.a, args.b))
    except Exception as e:  # noqa: BLE001 - onnxruntime raises its own types: one line
        print(f"compare_models.py: {' '.join(str(e).split())[:200]}", file=sys.stderr)
        return 1
    inputs = [{i.name: i.shape for i in s.get_inputs()} for s in (a, b)]
    if inputs[0].keys() != inputs[1].keys() or inputs[0].get("x") != inputs[1].get("x"):
        shown = [", ".join(f"{k} {v}" for k, v in i.items()) for i in inputs]
        print(f"compare_models.py: {args.a} and {args.b} take different inputs ({shown[0]}; "
              f"{shown[1]}): the window x and the input names must be the same", file=sys.stderr)
        return 1
    feed_a, feed_b = feeds(a, 1), feeds(b, 1)
    feed_b["x"] = feed_a["x"]  # the same window; each file its own state
    per_call(a, feed_a, 20)  # warm up
    per_call(b, feed_b, 20)
    ta, tb = alternate(args.rounds, lambda: per_call(a, feed_a, 50, time.process_time),
                       lambda: per_call(b, feed_b, 50, time.process_time))
    print(f"A {args.a}: {1e3 * ta:.3f} ms a window ({path_a}); B {args.b}: {1e3 * tb:.3f} ms "
          f"({path_b}); B / A {tb / ta:.3f}")
    return 0


def _session(path: str) -> tuple[ort.InferenceSession, str]:
    """``path``'s session as the runtime makes it, and how its custom nodes run."""
    so = session_options(1)
    native = kernels.register(so, path)
    sess = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
    return sess, ("native kernels" if native else "portable graph"
                  if kernels.has_custom_nodes(path) else "standard operators")


if __name__ == "__main__":
    sys.exit(main())
