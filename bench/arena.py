"""onnxruntime's CPU memory arena on and off, at several batch sizes, for an exported file.

    python bench/arena.py MODEL.onnx [--batch 1 --batch 256] [--rounds 7]

Two sessions of the file with the runtime's options (``session_options(1)``: one thread,
sequential, no spinning, no arena), one of them with the arena turned back on; per batch size
they run alternately, rounds of calls each (at least 20 windows a round), and the median CPU
time of this process per window is printed for both with their ratio (measured in the same run,
so the machine's load mostly cancels out; the runtime runs batch 1).
"""

from __future__ import annotations

import argparse
import time

import onnxruntime as ort
from batch_mix import alternate, feeds, per_call

from tactile.runtime.model import session_options


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--batch", type=int, action="append",
                    help="batch sizes (repeatable; default 1, 2 and 256)")
    ap.add_argument("--rounds", type=int, default=7, help="alternating rounds (default 7)")
    a = ap.parse_args()
    batches = a.batch or [1, 2, 256]
    if a.rounds < 1 or min(batches) < 1:
        ap.error("--batch and --rounds must be at least 1")
    with_arena = session_options(1)
    with_arena.enable_cpu_mem_arena = True
    plain = ort.InferenceSession(a.model, session_options(1), providers=["CPUExecutionProvider"])
    arena = ort.InferenceSession(a.model, with_arena, providers=["CPUExecutionProvider"])
    for b in batches:
        feed = feeds(plain, b)
        calls = max(1, -(-20 // b))  # at least 20 windows a round

        def per_window(sess: ort.InferenceSession, feed=feed, b=b, calls=calls) -> float:
            return per_call(sess, feed, calls, time.process_time) / b

        for s in (plain, arena):
            per_window(s)  # warm up
        p, r = alternate(a.rounds, lambda: per_window(plain), lambda: per_window(arena))
        print(f"batch {b}: no arena {1e3 * p:.3f} ms a window, arena {1e3 * r:.3f} ms; "
              f"no arena / arena {p / r:.3f}", flush=True)


if __name__ == "__main__":
    main()
