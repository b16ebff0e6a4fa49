"""Does a session run batch 1 slower after it has run another batch size?

    python bench/batch_mix.py MODEL.onnx [--batch 8] [--rounds 15]

Two sessions of the same file with the runtime's options (``session_options(1)``: one thread,
no CPU arena): one runs batch 1 only, the other runs batch 1 and then ``--batch``; then both
run batch 1 in alternating rounds of 50 calls. Prints the median time of a call of each and
their ratio (measured in the same run, so the machine's load cancels out).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import onnxruntime as ort

from tactile.runtime.model import session_options


def feeds(sess: ort.InferenceSession, batch: int) -> dict[str, np.ndarray]:
    """Random float32 inputs with every symbolic dimension set to ``batch``."""
    rng = np.random.default_rng(0)
    return {i.name: rng.standard_normal([d if isinstance(d, int) else batch for d in i.shape])
            .astype(np.float32) for i in sess.get_inputs()}


def per_call(sess: ort.InferenceSession, feed: dict, calls: int = 50,
             clock=time.perf_counter) -> float:
    """Seconds a call (by ``clock``) over ``calls`` calls of ``sess`` on ``feed``."""
    t0 = clock()
    for _ in range(calls):
        sess.run(None, feed)
    return (clock() - t0) / calls


def alternate(rounds: int, *timers) -> list[float]:
    """The median of each timer (a function returning a time) over ``rounds`` rounds that call
    the timers in turn, so that a change in the machine's load reaches them all alike."""
    times = [[] for _ in timers]
    for _ in range(rounds):
        for t, timer in zip(times, timers, strict=True):
            t.append(timer())
    return [float(np.median(t)) for t in times]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--batch", type=int, default=8, help="the other batch size (default 8)")
    ap.add_argument("--rounds", type=int, default=15, help="alternating rounds (default 15)")
    a = ap.parse_args()
    if a.batch < 1 or a.rounds < 1:
        ap.error("--batch and --rounds must be at least 1")
    mixed, pure = (ort.InferenceSession(a.model, session_options(1),
                                        providers=["CPUExecutionProvider"]) for _ in range(2))
    one, other = feeds(pure, 1), feeds(pure, a.batch)
    for s in (mixed, pure):
        per_call(s, one, 20)
    per_call(mixed, other, 20)
    m, p = alternate(a.rounds, lambda: per_call(mixed, one), lambda: per_call(pure, one))
    print(f"batch 1 after batch {a.batch}: {1e3 * m:.3f} ms a call; batch 1 only: "
          f"{1e3 * p:.3f} ms; ratio {m / p:.3f}")


if __name__ == "__main__":
    main()
