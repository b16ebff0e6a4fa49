"""Benchmark: the sparse coder (OMP as tensor ops) in onnxruntime against scikit-learn, one thread.

    python bench/sparse.py [--repeats 5] [--parity]

At the granular-media paper's sizes (vibration: 8 IMFs x 22 samples = 176 features, 200 atoms;
pressure: 5 x 5 = 25 features, 100 atoms; electrodes: 19 x 5 = 95 features, 100 atoms), with
scikit-learn's default non-zero count for each (a tenth of the features: 17, 2, 9) and with 10,
dictionaries learned by ``MiniBatchDictionaryLearning`` (one epoch over 600 windows of damped
tones plus noise), prints the time to code one window: scikit-learn's ``transform`` (its
default OMP) one window at a time and 256 at once, torch eager and onnxruntime (one thread) at
batch 1 and 256, each with its ratio to scikit-learn at the same batch; then the graph's export
time, node count and file size. Every implementation runs once per round (after a warm-up
round) and keeps its fastest round, so a slow spell of a shared host falls on all of them.
``OMP_NUM_THREADS=1`` keeps scikit-learn's BLAS to one thread too (set it before running).

``--parity`` instead prints the parity figures of ``tests/test_sparse.py``'s grid (atoms 20 /
100 / 200 x features 25 / 110 / 176 x non-zeros 1 / 3 / 5 / 10, learned and random unit-norm
dictionaries, 300 held-out float32 windows each), in torch and in onnxruntime: the share of
windows with the same non-zero atoms as scikit-learn, the largest difference relative to the
code's norm where they agree, and for every disagreement the float64 gap between the two
candidate atoms' correlations at the step where the codes part (relative to the largest).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np
import onnxruntime as ort
import torch
from sklearn.decomposition import MiniBatchDictionaryLearning
from sklearn.decomposition import SparseCoder as SkSparseCoder

from tactile.export.coder_graph import coder_graph
from tactile.training.sparse import SparseCoder, default_n_nonzero
from tactile.training.sparse_check import compare, structured

SIZES = (("vibration", 176, 200), ("pressure", 25, 100), ("electrodes", 95, 100))


def learn(atoms: int, features: int) -> MiniBatchDictionaryLearning:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return MiniBatchDictionaryLearning(n_components=atoms, batch_size=64, max_iter=1,
                                           random_state=0).fit(structured(600, features, features))


def session(model) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.log_severity_level = 3
    return ort.InferenceSession(model.SerializeToString(), opts,
                                providers=["CPUExecutionProvider"])


def bench_size(name: str, features: int, atoms: int, n: int, repeats: int) -> list[str]:
    m = learn(atoms, features).set_params(transform_n_nonzero_coefs=n)
    x = structured(256, features, seed=10_000 + features)
    coder = SparseCoder(m.components_, n)
    start = time.perf_counter()
    model = coder_graph(coder)
    t_export = time.perf_counter() - start
    s1, s256 = session(model), session(model)
    xt = torch.from_numpy(x)
    n1 = 32
    runs = {
        "sk_1": (lambda: [m.transform(x[i : i + 1]) for i in range(n1)], n1),
        "sk_256": (lambda: m.transform(x), 256),
        "torch_1": (lambda: [coder(xt[i : i + 1]) for i in range(n1)], n1),
        "torch_256": (lambda: coder(xt), 256),
        "ort_1": (lambda: [s1.run(None, {"x": x[i : i + 1]}) for i in range(n1)], n1),
        "ort_256": (lambda: s256.run(None, {"x": x}), 256),
    }
    best = {k: float("inf") for k in runs}
    with torch.no_grad():
        for round_ in range(repeats + 1):
            for k, (fn, count) in runs.items():
                start = time.perf_counter()
                fn()
                if round_:
                    best[k] = min(best[k], (time.perf_counter() - start) / count * 1e3)
    rows = [f"{name}: {features} features, {atoms} atoms, {n} non-zeros "
            f"(export {t_export:.1f} s, {len(model.graph.node)} nodes, "
            f"{model.ByteSize() / 1024:.0f} KiB)"]
    for batch in ("1", "256"):
        ref, tt, to = best[f"sk_{batch}"], best[f"torch_{batch}"], best[f"ort_{batch}"]
        rows.append(f"  batch {batch:>3}: scikit-learn {ref * 1e3:8.1f} us/window | "
                    f"torch {tt * 1e3:8.1f} us ({ref / tt:5.1f}x) | "
                    f"onnxruntime {to * 1e3:8.1f} us ({ref / to:5.1f}x)")
    return rows


def parity() -> list[str]:
    rows = []
    totals = {"torch": [0, 0, 0.0, []], "onnxruntime": [0, 0, 0.0, []]}
    for kind in ("learned", "random"):
        for k in (20, 100, 200):
            for f in (25, 110, 176):
                x = structured(300, f, seed=1000 + f)
                if kind == "learned":
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        m = MiniBatchDictionaryLearning(n_components=k, batch_size=64,
                                                        max_iter=1, random_state=0) \
                            .fit(structured(600, f, seed=f))
                    d = m.components_
                else:
                    d = np.random.default_rng(k * 1000 + f).standard_normal((k, f))
                    d /= np.linalg.norm(d, axis=1, keepdims=True)
                for n in (1, 3, 5, 10):
                    ref = SkSparseCoder(d, transform_algorithm="omp",
                                        transform_n_nonzero_coefs=n).transform(x)
                    coder = SparseCoder(d, n)
                    with torch.no_grad():
                        outs = {"torch": coder(torch.from_numpy(x)).numpy(),
                                "onnxruntime": session(coder_graph(coder)).run(None, {"x": x})[0]}
                    for impl, got in outs.items():
                        stats, t = compare(ref, got, d, x, n), totals[impl]
                        t[0] += stats["same"]
                        t[1] += stats["windows"]
                        t[2] = max(t[2], stats["max_rel"])
                        t[3] += [f"{kind} {k} atoms x {f} features, {n} non-zeros: "
                                 f"gap {gap:.1e}" for gap in stats["gaps"]]
    for impl, (agree, total, worst, ties) in totals.items():
        rows.append(f"{impl}: same atoms on {agree}/{total} windows ({agree / total:.3%}); "
                    f"max |diff| / ||code|| where they agree {worst:.1e}; "
                    f"{len(ties)} disagreements")
        rows += [f"  {t}" for t in ties]
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--parity", action="store_true", help="print the parity figures instead")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    if args.parity:
        for row in parity():
            print(row, flush=True)
        return 0
    print(f"sparse coder vs scikit-learn transform (OMP), one thread, time per window "
          f"(fastest of {args.repeats} rounds)")
    for name, features, atoms in SIZES:
        for n in sorted({default_n_nonzero(features, atoms), 10}):
            for row in bench_size(name, features, atoms, n, args.repeats):
                print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
