"""The native kernels (``tactile/native``): parity with independent references, edge inputs,
batch independence, and the C code under AddressSanitizer, UBSan and LeakSanitizer.

References: PyEMD (``EMD-signal`` 1.10.0, ``FIXE = n_sifts``) for the EMD in float64, the torch
``EMD`` module on float32 windows, scikit-learn's OMP (``SparseCoder(transform_algorithm=
"omp")``) for the codes. The tests skip, saying why, only when no library could be built;
under ``CI=true`` they fail instead.
"""

from __future__ import annotations

import ctypes
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from emd_cases import F32_FLIP_GAP, F32_FLIP_SHARE, F32_TOL, KINDS, near_tie_gap, pyemd, windows

from tactile import native
from tactile.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
NATIVE = REPO / "tactile" / "native"
EMD_TOL = 1e-9
"""Max |IMF or residue difference| / window std against PyEMD in float64 (both compute the same
float64 algorithm; the measured worst is about 1e-14)."""


def _build_in_place() -> str:
    """Build the library where the package looks for it (as ``pip install -e .`` does);
    returns the build's output (why it failed)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run(
            [sys.executable, "setup.py", "-q", "build_ext", "--inplace", "--build-temp", tmp,
             "--build-lib", tmp],
            cwd=REPO, capture_output=True, text=True, timeout=300,
        )
    return (out.stdout + out.stderr)[-400:]


@pytest.fixture(scope="module", autouse=True)
def library():
    """The built library, built now if the install did not (no compiler then)."""
    if native.disabled_by_env():
        pytest.skip(f"TACTILE_NATIVE={os.environ.get('TACTILE_NATIVE')}: the native kernels "
                    "are disabled")
    why = ""
    if native.library_path() is None:
        why = _build_in_place()
    if not native.available():
        msg = f"no native library could be built: {why.strip() or 'no C compiler'}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    return native.library_path()


def _ref(x: np.ndarray, n_imfs: int, n_sifts: int):
    """PyEMD's (IMFs, residue) of one float64 window, configured as the kernel claims."""
    return pyemd(np.asarray(x, dtype=np.float64), n_imfs, n_sifts)


def _random_windows(seed: int, count: int) -> list[np.ndarray]:
    """Random, quantised and random-walk signals of 50 to 2,200 samples."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        n = int(rng.integers(50, 2201))
        kind = i % 3
        if kind == 0:
            x = rng.standard_normal(n) * rng.uniform(0.1, 5)
        elif kind == 1:
            x = np.round(rng.uniform(1, 50) * np.sin(np.arange(n) * rng.uniform(0.01, 0.5))
                         + rng.normal(0, 2, n))
        else:
            x = rng.standard_normal(n).cumsum()
        out.append(x)
    return out


def _assert_pyemd_parity(x: np.ndarray, n_imfs: int, n_sifts: int) -> float:
    imfs, residue, n_valid = native.emd(x[None], n_imfs, n_sifts)
    ref_imfs, ref_res = _ref(x, n_imfs, n_sifts)
    k = int(n_valid[0])
    assert k == ref_imfs.shape[0], f"n_valid {k}, PyEMD {ref_imfs.shape[0]} (N={len(x)})"
    std = x.std() if x.std() > 0 else 1.0
    err = np.abs(residue[0] - ref_res).max()
    if k:
        err = max(err, np.abs(imfs[0, :k] - ref_imfs).max())
    assert not imfs[0, k:].any()
    rel = err / std
    assert rel <= EMD_TOL, f"{rel:.3g} of the std (N={len(x)})"
    return rel


@pytest.mark.parametrize("n_time", [50, 400, 1100])
def test_emd_matches_pyemd_on_the_shared_cases(n_time):
    worst = 0.0
    for i, kind in enumerate(KINDS):
        for x in windows(kind, n_time, 4, 300 + i):
            worst = max(worst, _assert_pyemd_parity(x, 4, 10))
    assert worst <= EMD_TOL


def test_emd_matches_pyemd_on_random_quantised_and_walk_signals_up_to_2200():
    for x in _random_windows(7, 12):
        _assert_pyemd_parity(x, 8, 10)
    # a few other settings: one sift, many sifts, one IMF
    for x, (k, s) in zip(_random_windows(8, 3), [(3, 1), (2, 40), (1, 10)]):
        _assert_pyemd_parity(x, k, s)


def test_emd_on_float32_windows_agrees_with_the_torch_module():
    torch = pytest.importorskip("torch", reason="the [train] extra (torch) is not installed")
    from tactile.training.emd import EMD

    torch.set_num_threads(1)
    for n_time, n_imfs, per_kind in ((50, 4, 16), (1100, 8, 3)):
        x = np.concatenate([windows(k, n_time, per_kind, 500 + i) for i, k in enumerate(KINDS)])
        std = x.std(1, keepdims=True)
        x = ((x - x.mean(1, keepdims=True)) / np.where(std > 0, std, 1.0)).astype(np.float32)
        imfs, residue, n_valid = native.emd(x, n_imfs, 10)
        assert imfs.dtype == residue.dtype == np.float32
        emd = EMD(n_imfs, 10)
        with torch.no_grad():
            t32 = [a.numpy() for a in emd(torch.as_tensor(x)[:, None])]
            t64 = [a.numpy() for a in emd(torch.as_tensor(x, dtype=torch.float64)[:, None])]
        # the same float64 algorithm on the same (float32) values: rounding apart
        k64, r64, n64 = native.emd(x.astype(np.float64), n_imfs, 10)
        np.testing.assert_array_equal(n64, t64[2][:, 0])
        np.testing.assert_allclose(k64, t64[0][:, 0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(r64, t64[1][:, 0], rtol=0, atol=1e-12)
        # float32 torch against the kernel
        s = x.astype(np.float64).std(1)
        rel = np.abs(imfs.astype(np.float64) - t32[0][:, 0]).max(axis=(1, 2)) / s
        off = np.flatnonzero((n_valid != t32[2][:, 0]) | (rel > F32_TOL))
        assert len(off) <= F32_FLIP_SHARE[n_time] * len(x), f"{len(off)} of {len(x)} windows off"
        for i in off:
            gap = near_tie_gap(x[i].astype(np.float64), n_imfs, 10)
            assert gap < F32_FLIP_GAP, f"window {i} (N={n_time}) off by {rel[i]:.3g} of its std, " \
                                       f"with no near-tie (closest gap {gap:.3g} std)"


def test_emd_result_is_bit_identical_whatever_the_batch():
    x = np.concatenate([windows(k, 120, 8, 900 + i) for i, k in enumerate(KINDS)])
    for dtype in (np.float64, np.float32):
        xd = x.astype(dtype)
        whole = native.emd(xd, 6, 10)
        for step in (1, 7):
            parts = [native.emd(xd[i : i + step], 6, 10) for i in range(0, len(xd), step)]
            for got, want in zip((np.concatenate(p) for p in zip(*parts)), whole):
                assert got.tobytes() == want.tobytes()


def test_kernels_run_concurrently_in_threads():
    """No global state: calls in four threads at once (ctypes releases the GIL) give the same
    bits as one after another."""
    from concurrent.futures import ThreadPoolExecutor

    x = [windows(k, 300, 6, 40 + i) for i, k in enumerate(KINDS)]
    rng = np.random.default_rng(4)
    d = _dictionary(rng, 40, 30)
    rows = [rng.standard_normal((50, 30)) for _ in range(6)]
    alone = [native.emd(w, 5, 10) for w in x] + [native.omp(r, d, d @ d.T, 6) for r in rows]
    with ThreadPoolExecutor(4) as pool:
        jobs = [pool.submit(native.emd, w, 5, 10) for w in x]
        jobs += [pool.submit(native.omp, r, d, d @ d.T, 6) for r in rows]
        together = [j.result() for j in jobs]
    for a, b in zip(alone, together):
        for u, v in zip(*(t if isinstance(t, tuple) else (t,) for t in (a, b))):
            assert u.tobytes() == v.tobytes()


@pytest.mark.parametrize("n_time", [0, 1, 2])
def test_emd_short_windows_have_no_imfs(n_time):
    x = np.arange(3 * n_time, dtype=np.float64).reshape(3, n_time)
    imfs, residue, n_valid = native.emd(x, 4, 10)
    assert imfs.shape == (3, 4, n_time) and not imfs.any()
    np.testing.assert_array_equal(residue, x)
    np.testing.assert_array_equal(n_valid, [0, 0, 0])


def test_emd_batch_zero_and_signals_without_extrema():
    imfs, residue, n_valid = native.emd(np.zeros((0, 50)), 4, 10)
    assert imfs.shape == (0, 4, 50) and residue.shape == (0, 50) and n_valid.shape == (0,)
    t = np.arange(50.0)
    x = np.stack([np.zeros(50), np.full(50, 7.0), 0.3 * t - 2, (t - 60.0) ** 2, np.zeros(50)])
    x[4, 20] = 1.0  # one extremum only
    imfs, residue, n_valid = native.emd(x, 4, 10)
    assert not imfs.any() and not n_valid.any()
    np.testing.assert_array_equal(residue, x)
    for row in x[1:]:  # PyEMD agrees (an all-zero row gives it no rows at all)
        _assert_pyemd_parity(row, 4, 10)


@pytest.mark.parametrize("scale", [1e-300, 1e-9, 1e6, 1e300])
def test_emd_amplitude_extremes_follow_the_torch_module(scale):
    torch = pytest.importorskip("torch", reason="the [train] extra (torch) is not installed")
    from tactile.training.emd import EMD

    x = windows("tones", 200, 4, 11) * scale
    imfs, residue, n_valid = native.emd(x, 4, 10)
    with torch.no_grad():
        ti, tr, tn = (a.numpy()[:, 0] for a in EMD(4, 10)(torch.as_tensor(x)[:, None]))
    np.testing.assert_array_equal(n_valid, tn)
    assert np.isfinite(imfs).all() and np.isfinite(residue).all()
    size = np.abs(x).max(1)[:, None, None]  # (x.std() underflows at 1e-300)
    assert (np.abs(imfs - ti) / size).max() <= 1e-12


def _call_c_emd(x: np.ndarray, n_imfs: int = 4, n_sifts: int = 10):
    """The f64 entry point directly (the wrapper refuses non-finite input before it)."""
    lib = ctypes.CDLL(str(native.library_path()))
    x = np.ascontiguousarray(x, dtype=np.float64)
    imfs = np.full((x.shape[0], n_imfs, x.shape[1]), 5.0)
    residue = np.full(x.shape, 5.0)
    n_valid = np.full(x.shape[0], 5, dtype=np.int64)
    p = ctypes.c_void_p
    status = lib.tactile_emd_f64(
        p(x.ctypes.data), ctypes.c_int64(x.shape[0]), ctypes.c_int64(x.shape[1]),
        ctypes.c_int32(n_imfs), ctypes.c_int32(n_sifts), p(imfs.ctypes.data),
        p(residue.ctypes.data), p(n_valid.ctypes.data))
    return status, imfs, residue, n_valid


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_emd_non_finite_rows_are_refused_and_left_undecomposed(bad):
    x = windows("tones", 60, 3, 12)
    with pytest.raises(ConfigError, match="NaN or inf"):
        native.emd(np.where(np.arange(60) == 30, bad, x), 4, 10)
    y = x.copy()
    y[1, 30] = bad
    status, imfs, residue, n_valid = _call_c_emd(y)
    assert status == 3
    assert n_valid[1] == 0 and not imfs[1].any()
    np.testing.assert_array_equal(residue[1], y[1])
    good = native.emd(x[[0, 2]], 4, 10)  # the other rows as if alone
    np.testing.assert_array_equal(imfs[[0, 2]], good[0])
    np.testing.assert_array_equal(n_valid[[0, 2]], good[2])


def test_emd_c_refuses_bad_arguments():
    x = np.zeros((2, 10))
    for n_imfs, n_sifts in ((0, 10), (17, 10), (4, 0), (4, 1001)):
        assert _call_c_emd(x, n_imfs, n_sifts)[0] == 1
    lib = ctypes.CDLL(str(native.library_path()))
    i64 = ctypes.c_int64
    assert lib.tactile_emd_f64(None, i64(2), i64(10), 4, 10, None, None, None) == 1
    assert lib.tactile_emd_f64(None, i64(-1), i64(10), 4, 10, None, None, None) == 1
    assert lib.tactile_emd_f64(None, i64(0), i64(10), 4, 10, None, None, None) == 0
    huge = i64(1 << 62)
    assert lib.tactile_emd_f64(None, huge, huge, 4, 10, None, None, None) == 1


@pytest.mark.parametrize(("args", "match"), [
    ((np.zeros(10), 4, 10), "2 dimensions"),
    ((np.zeros((2, 10), dtype=np.int64), 4, 10), "float32 or float64"),
    (([[0.0] * 10], 4, 10), "numpy array"),
    ((np.zeros((2, 10)), 0, 10), "n_imfs=0"),
    ((np.zeros((2, 10)), 4, 1001), "n_sifts=1001"),
    ((np.zeros((2, 10)), 4.0, 10), "must be an int"),
])
def test_wrapper_refuses_bad_input_in_one_line(args, match):
    with pytest.raises(ConfigError, match=match) as err:
        native.emd(*args)
    assert "\n" not in str(err.value)


def test_native_zero_disables_the_library(monkeypatch):
    monkeypatch.setenv("TACTILE_NATIVE", "0")
    assert native.library_path() is None and not native.available()
    with pytest.raises(native.NativeError, match="TACTILE_NATIVE=0"):
        native.emd(np.zeros((1, 10)), 4, 10)


# -- OMP ----------------------------------------------------------------------------------------

def _dictionary(rng, atoms=200, features=176) -> np.ndarray:
    d = rng.standard_normal((atoms, features))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _sklearn_codes(x: np.ndarray, d: np.ndarray, n_nonzero: int) -> np.ndarray:
    from sklearn.decomposition import SparseCoder

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # scikit-learn's early-exit warning
        coder = SparseCoder(d, transform_algorithm="omp", transform_n_nonzero_coefs=n_nonzero)
        return coder.transform(x)


def _greedy_path(x: np.ndarray, d: np.ndarray, n_nonzero: int) -> list[np.ndarray]:
    """Residual correlations before each step of a float64 OMP (no early exits): the
    explanation of a differing row, not a reference."""
    alphas, chosen = [], []
    r = x.copy()
    for _ in range(n_nonzero):
        a = d @ r
        alphas.append(a)
        chosen.append(int(np.argmax(np.abs(a))))
        sub = d[chosen]
        coef, *_ = np.linalg.lstsq(sub.T, x, rcond=None)
        r = x - sub.T @ coef
    return alphas


def _near_tie(x, d, n_nonzero, sk_support, got_support, rtol=1e-4) -> bool:
    """The two supports part at a step where the best atom of each side's remaining support
    has the largest |correlation| up to ``rtol`` (float32's rounding decides there)."""
    for a in _greedy_path(x.astype(np.float64), d.astype(np.float64), n_nonzero):
        best = np.abs(a).max()
        order = np.argsort(-np.abs(a), kind="stable")
        pick = order[0]
        if pick in sk_support and pick in got_support:
            continue
        rivals = [k for k in order[:10] if (k in sk_support) != (k in got_support)]
        return any(best - abs(a[k]) <= rtol * best for k in rivals)
    return False


def test_omp_matches_scikit_learn_in_float64():
    rng = np.random.default_rng(1)
    d = _dictionary(rng)
    x = rng.standard_normal((300, 176)) + (rng.random((300, 200)) < 0.05) * 3.0 @ d
    want = _sklearn_codes(x, d, 17)
    got = native.omp(x, d, d @ d.T, 17)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got != 0, want != 0)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)


def test_omp_matches_scikit_learn_on_float32_rows_up_to_near_ties():
    rng = np.random.default_rng(2)
    d = _dictionary(rng).astype(np.float32)
    x = (rng.standard_normal((2000, 176)) * 0.3
         + (rng.random((2000, 200)) < 0.04) * rng.standard_normal((2000, 200)) @ d)
    x = x.astype(np.float32)
    want = _sklearn_codes(x, d, 17)
    gram = (d.astype(np.float64) @ d.astype(np.float64).T).astype(np.float32)
    got = native.omp(x, d, gram, 17)
    assert got.dtype == np.float32
    same = ((got != 0) == (want != 0)).all(1)
    assert same.mean() >= 0.99, same.mean()
    scale = np.linalg.norm(want, axis=1)[same]
    assert (np.abs(got - want)[same].max(1) <= 1e-4 * np.maximum(scale, 1.0)).all()
    for i in np.flatnonzero(~same):
        assert _near_tie(x[i], d, 17, set(np.flatnonzero(want[i])), set(np.flatnonzero(got[i]))), \
            f"row {i}: other atoms than scikit-learn's without a near-tie"


def test_omp_ties_and_early_exits_follow_scikit_learn():
    rng = np.random.default_rng(3)
    d = _dictionary(rng, 30, 12)
    d[7] = d[3]  # an exact tie: scikit-learn takes the first in its working order
    d[11] = -d[5]
    d[20] *= 1e-9  # an atom of tiny norm
    x = np.concatenate([rng.standard_normal((40, 12)), d[[3, 5, 20]] * 2.0, np.zeros((2, 12))])
    for n_nonzero in (1, 5, 12, 30):
        want = _sklearn_codes(x, d, n_nonzero)
        got = native.omp(x, d, d @ d.T, n_nonzero)
        np.testing.assert_array_equal(got != 0, want != 0)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)


def _has_avx2() -> bool:
    try:
        return " avx2" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


@pytest.mark.skipif(not _has_avx2(), reason="the AVX2 copy of the OMP loops runs only on x86-64 "
                    "processors with AVX2 (this one has none, or no /proc/cpuinfo)")
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_omp_avx2_copy_gives_the_baseline_bits(monkeypatch, dtype):
    """omp.c's hot loops exist twice on x86-64: 2 and 4 doubles a vector. They must compute
    the same sums in the same order: the same codes, bit for bit, at sizes that fill the
    vector blocks and sizes that leave remainders."""
    rng = np.random.default_rng(11)
    for atoms, features, n_nonzero, rows in ((200, 176, 17, 203), (100, 95, 9, 50),
                                             (50, 21, 6, 23), (37, 13, 7, 9), (5, 3, 3, 4)):
        d = _dictionary(rng, atoms, features).astype(dtype)
        gram = (d.astype(np.float64) @ d.astype(np.float64).T).astype(dtype)
        x = (rng.standard_normal((rows, features))
             + (rng.random((rows, atoms)) < 0.05) * 2.0 @ d).astype(dtype)
        monkeypatch.delenv("TACTILE_NATIVE_SIMD", raising=False)
        fast = native.omp(x, d, gram, n_nonzero)
        monkeypatch.setenv("TACTILE_NATIVE_SIMD", "base")
        base = native.omp(x, d, gram, n_nonzero)
        assert (fast != 0).sum() > rows  # codes were computed
        assert fast.tobytes() == base.tobytes(), (atoms, features)


def test_omp_refuses_bad_input():
    d = np.eye(4)
    with pytest.raises(ConfigError, match="n_nonzero=5"):
        native.omp(np.zeros((1, 4)), d, d, 5)
    with pytest.raises(ConfigError, match="features"):
        native.omp(np.zeros((1, 3)), d, d, 2)
    with pytest.raises(ConfigError, match="gram"):
        native.omp(np.zeros((1, 4)), d, np.eye(3), 2)
    with pytest.raises(ConfigError, match="NaN or inf"):
        native.omp(np.full((1, 4), np.nan), d, d, 2)
    assert native.omp(np.zeros((0, 4)), d, d, 2).shape == (0, 4)


# -- the C code under the sanitizers -------------------------------------------------------------

SAN_MAIN = NATIVE / "fuzz" / "edge_main.c"
SANITIZE = ("-fsanitize=address,undefined", "-fno-sanitize-recover=all",
            "-fno-omit-frame-pointer", "-g", "-O1")
WARNINGS = ("-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror")


def test_c_kernels_under_address_undefined_and_leak_sanitizers(tmp_path):
    """gcc builds the kernels with the edge-input program (``fuzz/edge_main.c``) and runs it
    with LeakSanitizer on: no report, and the program's own checks pass."""
    cc = shlex.split(os.environ.get("CC", "")) or ["gcc"]
    if shutil.which(cc[0]) is None:
        msg = f"no C compiler ({cc[0]}): the sanitized kernels are not tested"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    exe = tmp_path / "edge_san"
    build = subprocess.run(
        [*cc, *WARNINGS, *SANITIZE, f"-I{NATIVE}", str(NATIVE / "emd.c"), str(NATIVE / "omp.c"),
         str(SAN_MAIN), "-o", str(exe), "-lm"], capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr[-2000:]
    env = {**os.environ, "ASAN_OPTIONS": "detect_leaks=1:abort_on_error=0",
           "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1"}
    for simd in ("", "base"):  # the copy this processor picks, and the baseline copy
        run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=600,
                             env={**env, "TACTILE_NATIVE_SIMD": simd})
        report = run.stdout + run.stderr
        assert run.returncode == 0, report[-3000:]
        assert "Sanitizer" not in report and "runtime error" not in report, report[-3000:]
        assert run.stdout.strip().splitlines()[-1].startswith("edge cases passed:"), report[-500:]
