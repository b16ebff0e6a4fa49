"""Benchmark: the native kernels (C, through ctypes) against PyEMD, the torch EMD and
scikit-learn's OMP, one thread.

    python bench/native.py [--repeats 5]

Cases, each at batch 1 (one window per call), the same windows for every implementation:

* EMD 1 x 1,100 samples, 8 IMFs x 10 sifts (the BioTac's vibration window);
* EMD 8 x 50 samples (the pen's 8 channels), 4 IMFs x 10 sifts; PyEMD loops over the channels;
* OMP of 46 rows x 176 features on 200 atoms, 17 non-zeros (one vibration image of the granular
  model), float32: the kernel, scikit-learn's ``SparseCoder(transform_algorithm="omp")``
  transform and the torch ``SparseCoder``; and the kernel's baseline loops
  (``TACTILE_NATIVE_SIMD=base``: SSE2 on x86-64) beside the AVX2 ones it picks where the
  processor has them (the same on processors without).

Prints milliseconds per call and each one's time over the kernel's, all measured in this run:
every implementation runs once per round (after a warm-up round) and keeps its fastest round,
so a slow spell of a shared host falls on all of them alike. The EMD windows are EMD_SPEC §5's
z-scored test signal (three tones plus noise); the kernel runs on float32 windows as the
exported graph does (float64 inside).
"""

from __future__ import annotations

import os
import sys
import time
import warnings

import numpy as np
import torch
from PyEMD import EMD as PyEMD
from sklearn.decomposition import SparseCoder as SkCoder
from threadpoolctl import threadpool_limits

from tactile import native
from tactile.training.emd import EMD
from tactile.training.sparse import SparseCoder

N_SIFTS = 10


def signal_windows(n_windows: int, n_channels: int, n_time: int, seed: int = 0) -> np.ndarray:
    """(W, C, T) z-scored windows of three tones plus noise at 100 Hz (EMD_SPEC §5)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_windows * n_time) / 100.0
    out = np.empty((n_windows, n_channels, n_time))
    for c in range(n_channels):
        ph = rng.uniform(0, 2 * np.pi, 3)
        s = (np.sin(2 * np.pi * 1.3 * t + ph[0]) + 0.6 * np.sin(2 * np.pi * 5.7 * t + ph[1])
             + 0.4 * np.sin(2 * np.pi * 17 * t + ph[2]) + 0.25 * rng.standard_normal(t.size))
        w = s.reshape(n_windows, n_time)
        out[:, c] = (w - w.mean(1, keepdims=True)) / w.std(1, keepdims=True)
    return out


def race(fns: dict, repeats: int, calls: int) -> dict[str, float]:
    """Milliseconds per call of each function, the fastest of ``repeats`` interleaved rounds of
    ``calls`` calls (after a warm-up round), as CPU time of the calling thread: every
    implementation here runs on it (torch and onnxruntime on one thread), so that a loaded
    machine's waiting is left out."""
    best = dict.fromkeys(fns, np.inf)
    for round_ in range(repeats + 1):
        for name, fn in fns.items():
            start = time.thread_time()
            for i in range(calls):
                fn(i)
            ms = (time.thread_time() - start) / calls * 1e3
            if round_:
                best[name] = min(best[name], ms)
    return best


def emd_case(n_channels: int, n_time: int, n_imfs: int, repeats: int) -> list[str]:
    calls = 4 if n_time > 500 else 20
    x64 = signal_windows(calls, n_channels, n_time)
    x32 = x64.astype(np.float32)
    ref = PyEMD(FIXE=N_SIFTS, spline_kind="cubic", nbsym=2, extrema_detection="simple")
    module = EMD(n_imfs, N_SIFTS)
    xt = torch.as_tensor(x32)

    def pyemd(i):
        for c in range(n_channels):
            ref.emd(x64[i, c], max_imf=n_imfs)

    def torch_emd(i):
        with torch.no_grad():
            module(xt[i : i + 1])

    fns = {
        "native f32": lambda i: native.emd(x32[i], n_imfs, N_SIFTS),
        "native f64": lambda i: native.emd(x64[i], n_imfs, N_SIFTS),
        "torch EMD f32": torch_emd,
        "PyEMD": pyemd,
    }
    return table(f"EMD {n_channels} x {n_time}, {n_imfs} IMFs x {N_SIFTS} sifts, batch 1",
                 race(fns, repeats, calls))


def omp_rows(calls: int, rows: int, features: int, atoms: int) -> tuple[np.ndarray, np.ndarray]:
    """A unit-norm dictionary (atoms, features) and ``calls`` batches of rows (calls, rows,
    features), float32, seeded: a few atoms of each row's mix plus noise."""
    rng = np.random.default_rng(0)
    d = rng.standard_normal((atoms, features))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    x = (rng.standard_normal((calls, rows, features)) * 0.3
         + ((rng.random((calls, rows, atoms)) < 0.05) * rng.standard_normal((calls, rows, atoms)))
         @ d).astype(np.float32)
    return d, x


def omp_case(repeats: int, rows: int = 46, features: int = 176, atoms: int = 200,
             n_nonzero: int = 17) -> list[str]:
    calls = 10
    d, x = omp_rows(calls, rows, features, atoms)
    gram = (d.astype(np.float64) @ d.astype(np.float64).T).astype(np.float32)
    sk = SkCoder(d, transform_algorithm="omp", transform_n_nonzero_coefs=n_nonzero)
    coder = SparseCoder(d, n_nonzero)
    xt = torch.as_tensor(x)

    def torch_omp(i):
        with torch.no_grad():
            coder(xt[i])

    def baseline_copy(i):  # the kernel's baseline vector loops where an AVX2 copy would run
        before = os.environ.get("TACTILE_NATIVE_SIMD")
        os.environ["TACTILE_NATIVE_SIMD"] = "base"
        try:
            native.omp(x[i], d, gram, n_nonzero)
        finally:
            if before is None:
                os.environ.pop("TACTILE_NATIVE_SIMD")
            else:
                os.environ["TACTILE_NATIVE_SIMD"] = before

    fns = {
        "native f32": lambda i: native.omp(x[i], d, gram, n_nonzero),
        "native, baseline": baseline_copy,
        "torch SparseCoder": torch_omp,
        "scikit-learn": lambda i: sk.transform(x[i]),
    }
    return table(f"OMP {rows} rows x {features} features, {atoms} atoms, {n_nonzero} non-zeros",
                 race(fns, repeats, calls))


def table(title: str, ms: dict[str, float]) -> list[str]:
    base = ms["native f32"]
    lines = [title, f"  {'implementation':<20} {'ms/call':>10} {'x native f32':>13}"]
    lines += [f"  {name:<20} {t:>10.3f} {t / base:>13.1f}" for name, t in ms.items()]
    return lines


def main(argv: list[str] | None = None) -> int:
    from tactile.cli import Parser, int_in

    parser = Parser(prog="native.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int_in(1), default=5, help="timed rounds (fastest kept)")
    args = parser.parse_args(argv)
    if not native.available():
        print("the native kernels are not built (pip install -e . with a C compiler)",
              file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", RuntimeWarning)  # scikit-learn's OMP early-exit warning
    print(f"torch {torch.__version__}, library {native.library_path().name}, one thread",
          file=sys.stderr)
    with threadpool_limits(1):
        lines = emd_case(1, 1100, 8, args.repeats) + emd_case(8, 50, 4, args.repeats)
        lines += omp_case(args.repeats)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
