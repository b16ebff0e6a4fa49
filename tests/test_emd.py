"""EMD as tensor ops: pieces, known signals and float64 parity against PyEMD.

Expected values come from PyEMD / scipy in float64, computed here. Tolerances are stated where
used: 1e-9 x window std for the decomposition (the fixed-shape algorithm agrees to ~1e-14),
1e-10 relative for single splines.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from emd_cases import KINDS, compare, parity_set, pyemd, run_torch, windows
from PyEMD import EMD as PyEMD
from PyEMD.splines import cubic_spline_3pts
from scipy.interpolate import CubicSpline

from tactile.errors import ConfigError
from tactile.training.emd import EMD, EMDConfig
from tactile.training.emd.boundary import boundary_knots, side_coordinates
from tactile.training.emd.envelope import evaluate, segment_index
from tactile.training.emd.extrema import extrema_marks, find_extrema
from tactile.training.emd.knots import (
    assemble,
    end_extrema,
    end_extrema_topk,
    extrema_counts,
    n_slots,
    past_dummies,
)
from tactile.training.emd.sift import envelopes, prepare_knots, prepare_system, sift
from tactile.training.emd.spline import LARGE_ROWS, pcr_solve, spacings, spline_system

PARITY_TOL = 1e-9  # x window std
REF = PyEMD(FIXE=10, spline_kind="cubic", nbsym=2, extrema_detection="simple")


def _small_windows(seed: int, count: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        n = int(rng.integers(3, 30))
        if rng.random() < 0.5:
            out.append(rng.integers(-2, 3, n).astype(np.float64))  # many ties
        else:
            out.append(np.round(rng.standard_normal(n).cumsum()))
    return out


# -- settings -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs", [{"n_imfs": 0}, {"n_sifts": 0}, {"n_imfs": 17}, {"n_sifts": 2.0}, {"n_imfs": True}]
)
def test_bad_settings_raise_one_line_config_error(kwargs):
    with pytest.raises(ConfigError) as err:
        EMD(**kwargs)
    assert "\n" not in str(err.value) and str(err.value)


def test_config_is_frozen_with_defaults_for_50_sample_windows():
    cfg = EMD().config
    assert (cfg.n_imfs, cfg.n_sifts) == (4, 10)
    with pytest.raises(AttributeError):
        cfg.n_imfs = 3  # type: ignore[misc]
    assert EMDConfig(2, 5) == EMDConfig(n_imfs=2, n_sifts=5)


# -- extrema --------------------------------------------------------------------------------


def test_extrema_match_pyemd_on_tied_signals():
    wins = _small_windows(1, 3000)
    for x in wins:
        got = find_extrema(torch.tensor(x)[None])[0].numpy()  # (N,)
        max_pos, _, min_pos, _, _ = REF._find_extrema_simple(np.arange(len(x), dtype=float), x)
        assert np.array_equal(np.nonzero(got > 0)[0], max_pos.astype(int)), x
        assert np.array_equal(np.nonzero(got < 0)[0], min_pos.astype(int)), x


@pytest.mark.parametrize(
    ("x", "maxima", "minima"),
    [
        ([0, 1, 1, 0, 2, 0, 1], [4], [3, 5]),  # quirk 1: run starting at difference 1 dropped
        ([0, 0, 1, 0, -1, 0, -1], [2, 5], [0, 4]),  # quirk 2: wrap-around slope, minimum at 0
        ([0, 1, 0, 2, 2, 2], [1], [2]),  # quirk 3: run reaching the end dropped
        ([0, -1, 2, 2, 0, 3, 3, 0], [2, 6], [1, 4]),  # midpoints 2.5 -> 2, 5.5 -> 6
    ],
)
def test_extrema_plateau_quirks(x, maxima, minima):
    x = np.asarray(x, dtype=np.float64)
    max_pos, _, min_pos, _, _ = REF._find_extrema_simple(np.arange(len(x), dtype=float), x)
    assert list(max_pos) == maxima and list(min_pos) == minima  # the quirk is PyEMD's
    got = find_extrema(torch.tensor(x)[None])[0].numpy()
    assert list(np.nonzero(got > 0)[0]) == maxima and list(np.nonzero(got < 0)[0]) == minima


# -- boundary knots and assembly ------------------------------------------------------------


def _case(x: np.ndarray, pmax: np.ndarray, pmin: np.ndarray) -> tuple[str, str]:
    """Which row of EMD_SPEC §1.5's tables applies at each end (plus 'f' for a fallback)."""
    first_max = pmax[0] < pmin[0]
    f, g = (pmax, pmin) if first_max else (pmin, pmax)
    sigma = 1.0 if first_max else -1.0
    one = sigma * (x[0] - x[g[0]]) > 0
    left = ("A" if first_max else "B") + ("1" if one else "2")
    if one and min(f[min(2, len(f) - 1)], g[min(1, len(g) - 1)]) < 2 * f[0]:
        left += "f"
    n1 = len(x) - 1
    last_max = pmax[-1] > pmin[-1]
    f, g = (n1 - pmax[::-1], n1 - pmin[::-1]) if last_max else (n1 - pmin[::-1], n1 - pmax[::-1])
    sigma = 1.0 if last_max else -1.0
    one = sigma * (x[-1] - x[n1 - g[0]]) > 0
    right = ("D" if last_max else "C") + ("1" if one else "2")
    if one and min(f[min(2, len(f) - 1)], g[min(1, len(g) - 1)]) < 2 * f[0]:
        right += "f"
    return left, right


def _assert_same_knots(got, bxy, bv):
    """``got`` has the validity ``bv`` and the knots ``bxy`` wherever they are valid (the
    others go to the dump slot, never used)."""
    gxy, gv = got
    assert torch.equal(gv, bv)
    keep = bv.bool().expand_as(bxy)
    assert torch.equal(gxy[keep], bxy[keep])


def test_boundary_knots_match_pyemd_in_every_case():
    rng = np.random.default_rng(2)
    seen: set[str] = set()
    checked = 0
    noise = [rng.standard_normal(int(rng.integers(5, 40))) for _ in range(1500)]
    wins = _small_windows(3, 2500) + noise
    for x in wins:
        t = np.arange(len(x), dtype=float)
        pmax, vmax, pmin, vmin, _ = REF._find_extrema_simple(t, x)
        if len(pmax) + len(pmin) < 3:
            continue
        ref_max, ref_min = REF.prepare_points_simple(t, x, pmax, vmax, pmin, vmin)
        h = torch.tensor(x)[None]
        marks = extrema_marks(h)  # (2, 1, N)
        cnt, n = extrema_counts(marks)
        p, v = end_extrema(h, cnt, n)
        q = side_coordinates(p, len(x))
        bxy, bv = boundary_knots(h, q, v, n)
        # The end extrema by TopK (the exported small-batch body's) give the same knots.
        tq, tv, tn = end_extrema_topk(h, marks)
        assert torch.equal(tn, n)
        _assert_same_knots(boundary_knots(h, tq, tv, tn), bxy, bv)
        # The row-last layout (the exported large-batch body's) gives the same bits.
        last = (0, 2, 3, 1)
        txy, tv = boundary_knots(h, q.permute(last), v.permute(last), n.permute(last), True)
        assert torch.equal(txy.transpose(-1, -2), bxy) and torch.equal(tv.transpose(-1, -2), bv)
        (kx, ky), j1, _ = assemble(h, marks, bxy, bv)
        for env, ref in ((0, ref_max), (1, ref_min)):
            hi = int(j1[env, 0, 0]) + 1  # knots in slots 1 .. j1, a placeholder in slot 0
            assert np.array_equal(kx[env, 0, 1:hi].numpy(), ref[0]), (x, env)
            assert np.array_equal(2 * ky[env, 0, 1:hi].numpy(), ref[1]), (x, env)  # half values
            # The placeholder and the dummies keep spacings positive.
            assert np.all(np.diff(kx[env, 0].numpy()) > 0)
            assert hi < kx.shape[-1]  # the last slot always holds a dummy
        hk, _ = spacings(torch.stack([kx, ky]), past_dummies(len(x)))
        assert torch.all(hk[..., -1] == 1.0)  # its placeholder spacing, as the dummies' own
        seen.update(_case(x, pmax.astype(int), pmin.astype(int)))
        checked += 1
    assert checked > 2000
    cases = {"A1", "A2", "B1", "B2", "C1", "C2", "D1", "D2", "A1f", "B1f", "C1f", "D1f"}
    assert cases <= seen, cases - seen


# -- spline solve and evaluation ------------------------------------------------------------


def test_segment_from_running_count_equals_a_search_over_the_knots():
    """segment_index reads the placement's running count (left mirrored knots counted at every
    sample, right ones at none); after clamping it must equal a search over the actual knot
    positions for every envelope of every row that is still sifted (> 2 extrema)."""
    rng = np.random.default_rng(11)
    wins = _small_windows(12, 2000) + [rng.standard_normal(int(rng.integers(5, 60)))
                                        for _ in range(1000)]
    for _ in range(1500):  # one to two periods: envelopes of 1-2 extrema (natural splines)
        n_time = int(rng.integers(6, 60))
        ph = 2 * np.pi * (rng.uniform(0.8, 2.0) * np.arange(n_time) / n_time + rng.uniform())
        wins.append(np.sin(ph) + 0.05 * rng.standard_normal(n_time))
    checked = natural = 0
    for x in wins:
        h = torch.tensor(x)[None]
        marks = extrema_marks(h)
        cnt, n = extrema_counts(marks)
        if int(n.sum()) <= 2:
            continue
        p, v = end_extrema(h, cnt, n)
        bxy, bv = boundary_knots(h, side_coordinates(p, len(x)), v, n)
        xy, j1, ks = assemble(h, marks, bxy, bv)
        got = segment_index(ks, j1)[0, :, 0].numpy()  # (2, N)
        t = np.arange(len(x))
        for env in range(2):
            last = int(j1[env, 0, 0])  # knots in slots 1 .. last
            xs = xy[0, env, 0, 1 : last + 1].numpy()
            lo, hi = (2, last - 2) if last >= 4 else (1, 2)
            want = np.clip(np.searchsorted(xs, t, side="right"), lo, hi)
            assert np.array_equal(got[env], want), (x, env)
            checked += 1
            natural += last == 3  # three knots
    assert checked > 5000 and natural > 100, (checked, natural)  # both spline kinds seen


def test_pcr_solves_diagonally_dominant_tridiagonal_systems():
    rng = np.random.default_rng(4)
    k = 37
    a = rng.uniform(-1, 1, (50, k))
    c = rng.uniform(-1, 1, (50, k))
    a[:, 0] = 0
    c[:, -1] = 0
    b = np.abs(a) + np.abs(c) + rng.uniform(0.05, 1, (50, k))
    r = rng.standard_normal((50, k))
    got = pcr_solve(torch.tensor(np.stack([a / b, c / b, r / b])))[0].numpy()  # (50, K)
    for i in range(50):
        mat = np.diag(b[i]) + np.diag(a[i, 1:], -1) + np.diag(c[i, :-1], 1)
        np.testing.assert_allclose(got[i], np.linalg.solve(mat, r[i]), rtol=1e-12, atol=1e-12)


def _cut_envelopes(h: torch.Tensor, cut: int = 0) -> torch.Tensor:
    """(2, R, N) half envelopes of ``h`` solved on the knots cut to ``knot_width - cut`` slots,
    or on all K slots (``cut=None``)."""
    marks = extrema_marks(h)
    xy, j1, ks, _, width = prepare_knots(h, marks)
    if cut is not None:
        xy = xy[..., : int(width) - cut]
    system, hk, sl = prepare_system(xy, j1, int(h.shape[-1]))
    return evaluate(h, xy, pcr_solve(system, j1), segment_index(ks, j1), hk, sl)[0]


def test_knot_width_cut_changes_no_bit():
    """A sift solves and evaluates its splines on the knots cut to ``knot_width`` (the batch's
    most knots + 2): every row gets the same values as on all K slots and as alone, whatever
    the other rows' knot counts."""
    rng = np.random.default_rng(6)
    t = np.arange(400)
    x = np.stack([
        rng.standard_normal(400),  # ~130 knots per envelope
        np.sin(2 * np.pi * t / 37) + 0.05 * rng.standard_normal(400),
        np.sin(2 * np.pi * t / 150),  # a few knots
        np.round(3 * np.sin(2 * np.pi * t / 90) + rng.standard_normal(400).cumsum() / 4),  # ties
        np.sin(2 * np.pi * t / 500),  # one extremum: 3-knot natural splines
    ])
    h = torch.tensor(x)
    full = _cut_envelopes(h, cut=None)
    assert torch.equal(_cut_envelopes(h), full)
    for row in range(len(x)):  # alone: a narrower cut
        assert torch.equal(_cut_envelopes(h[row : row + 1])[:, 0], full[:, row]), row
    # Two slots fewer (max(j1)) cut the last knot of the row with most knots: the test can tell.
    assert not torch.equal(_cut_envelopes(h, cut=2), full)


@pytest.mark.parametrize("n_knots", [3, 4, 5, 9, 20])
def test_spline_pieces_match_scipy_not_a_knot_and_natural_3_point(n_knots):
    rng = np.random.default_rng(n_knots)
    n_time = 60
    k = n_slots(n_time)
    for _ in range(30):
        inner = np.sort(rng.choice(np.arange(1, n_time - 1), n_knots - 2, replace=False))
        ends = [-int(rng.integers(0, 9))], [n_time - 1 + int(rng.integers(0, 9))]
        xs = np.concatenate([ends[0], inner, ends[1]])
        ys = rng.standard_normal(n_knots)
        # Slot 0 a placeholder below the knots, then the knots, then dummies above them.
        dummies = 4 * n_time + np.arange(k - 1 - n_knots)
        x = np.concatenate([[-4 * n_time], xs, dummies]).astype(np.float64)
        y = np.concatenate([[0.0], ys, np.zeros(k - 1 - n_knots)])
        xy = torch.tensor(np.stack([x, y])).reshape(2, 1, 1, k).repeat(1, 2, 1, 1)  # (2, 2, 1, K)
        j1 = torch.full((2, 1, 1), float(n_knots), dtype=torch.float64)
        system = spline_system(xy, j1)
        m = pcr_solve(system)
        t = np.arange(n_time, dtype=np.float64)
        seg = np.clip(np.searchsorted(xs, t, side="right") - 1, 0, n_knots - 2)
        if n_knots >= 4:  # outer segments evaluate their neighbour's cubic (same polynomial)
            seg = np.clip(seg, 1, n_knots - 3)
        seg_t = torch.tensor(seg + 1).reshape(1, 1, 1, -1).repeat(1, 2, 1, 1)  # knot -> slot
        got = evaluate(torch.zeros(1, n_time), xy, m, seg_t)[0, 0, 0].numpy()
        if n_knots > 3:
            want = CubicSpline(xs, ys)(t)
        else:
            want = cubic_spline_3pts(xs.astype(float), ys, t)[1]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 * np.abs(ys).max())


def test_one_sift_matches_pyemd_envelopes():
    rng = np.random.default_rng(5)
    x = np.concatenate([windows(kind, 50, 40, 10 + i) for i, kind in enumerate(KINDS)])
    x = np.concatenate([x, rng.standard_normal((100, 50))])
    env, n_ext = envelopes(torch.tensor(x))
    h, active = sift(torch.tensor(x), torch.ones(len(x), 1, dtype=torch.bool))
    t = np.arange(50, dtype=float)
    for i in range(len(x)):
        pmax, _, pmin, _, _ = REF._find_extrema_simple(t, x[i])
        assert int(n_ext[i]) == len(pmax) + len(pmin)
        assert bool(active[i]) == (len(pmax) + len(pmin) > 2)
        if not active[i]:
            assert torch.equal(h[i], torch.tensor(x[i]))
            continue
        upper, lower, _, _ = REF.extract_max_min_spline(t, x[i])
        tol = 1e-12 * max(1.0, np.abs(x[i]).max())
        np.testing.assert_allclose(env[0, i].numpy(), upper, rtol=0, atol=tol)
        np.testing.assert_allclose(env[1, i].numpy(), lower, rtol=0, atol=tol)
        np.testing.assert_allclose(h[i].numpy(), x[i] - 0.5 * (upper + lower), rtol=0, atol=tol)


# -- the decomposition ----------------------------------------------------------------------

PARITY_SETS = [(50, 300), (200, 80), (1000, 25)]  # (length, windows per kind): 2025 windows
"""Shared with test_emd_onnx.py, which checks onnxruntime on the same windows."""


@pytest.mark.parametrize("layout", ["large", "small"])
@pytest.mark.parametrize(("n_time", "per_kind"), PARITY_SETS)
def test_float64_parity_with_pyemd(n_time, per_kind, layout):
    """All windows in one call (the many-row layout), then in calls below LARGE_ROWS."""
    x, refs = parity_set(n_time, per_kind)
    assert len(x) >= LARGE_ROWS
    imfs, residue, n_valid = run_torch(x, chunk=None if layout == "large" else LARGE_ROWS // 2)
    same, rel = compare(x, imfs, residue, n_valid, refs)
    assert same.all(), f"IMF count differs from PyEMD in {np.count_nonzero(~same)} windows"
    assert rel.max() <= PARITY_TOL, rel.max()
    np.testing.assert_allclose(residue, x - imfs.sum(1), rtol=0, atol=1e-12 * np.abs(x).max())
    assert (imfs[np.arange(N := imfs.shape[1])[None, :] >= n_valid[:, None]] == 0).all(), N


def test_a_tone_gives_itself_as_imf_1():
    t = np.arange(200, dtype=np.float64)
    tone = 1.5 * np.sin(2 * np.pi * t / 20.0 + 0.3)
    imfs, residue, n_valid = run_torch(tone[None])
    assert n_valid[0] >= 1
    assert np.abs(imfs[0, 0] - tone)[20:-20].max() < 0.01 * 1.5  # edges carry mirroring error
    assert np.abs(imfs[0, 0] - tone).max() < 0.1 * 1.5
    ref_imfs, _ = pyemd(tone)
    np.testing.assert_allclose(imfs[0, 0], ref_imfs[0], rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "x",
    [
        np.linspace(-3.0, 5.0, 50),  # a line: no extremum, no IMF
        np.full(50, 7.25),  # constant
        np.zeros(50),  # all zero: PyEMD returns no rows at all
        np.array([0.0, 1.0, 2.0]),  # too short for an extremum
        np.array([0.0, 1.0, 0.0, 1.0]),  # 2 extrema: no IMF
        np.linspace(0, 1, 50) ** 2,  # monotonic curve
    ],
)
def test_signals_without_imfs_return_the_input_as_residue(x):
    imfs, residue, n_valid = run_torch(x[None])
    assert n_valid[0] == 0 and (imfs == 0).all()
    assert np.array_equal(residue[0], x)
    assert pyemd(x)[0].shape[0] == 0


@pytest.mark.parametrize("n_time", [1, 2])
def test_windows_shorter_than_3_samples_have_no_imfs(n_time):
    x = torch.arange(3 * 2 * n_time, dtype=torch.float32).reshape(3, 2, n_time)
    imfs, residue, n_valid = EMD()(x)
    assert imfs.shape == (3, 2, 4, n_time) and (imfs == 0).all()
    assert torch.equal(residue, x) and (n_valid == 0).all() and n_valid.dtype == torch.int64


@pytest.mark.parametrize("scale", [1e-7, 1e-4, 1.0, 1e4, 1e9])
def test_amplitude_extremes_follow_pyemd_absolute_thresholds(scale):
    """PyEMD's end thresholds are absolute: tiny windows stop early, huge ones do not."""
    base = windows("tones", 50, 40, 7)
    x = base * scale
    imfs, residue, n_valid = run_torch(x)
    same, rel = compare(x, imfs, residue, n_valid)
    assert same.all() and rel.max() <= PARITY_TOL
    if scale <= 1e-4:  # below range_thr after one IMF
        assert n_valid.max() <= 1


def test_shapes_dtypes_and_batch_independence():
    x = torch.tensor(windows("tones", 50, 12, 8), dtype=torch.float32).reshape(3, 4, 50)
    imfs, residue, n_valid = EMD()(x)
    assert imfs.shape == (3, 4, 4, 50) and imfs.dtype == torch.float32
    assert residue.shape == (3, 4, 50) and n_valid.shape == (3, 4) and n_valid.dtype == torch.int64
    one = EMD()(x[1:2])
    assert torch.equal(one[0], imfs[1:2]) and torch.equal(one[2], n_valid[1:2])


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_input_is_rejected(bad):
    x = torch.zeros(1, 1, 50)
    x[0, 0, 10] = bad
    with pytest.raises(ValueError, match="NaN or inf"):
        EMD()(x)


@pytest.mark.parametrize("shape", [(50,), (2, 50), (1, 1, 1, 50)])
def test_wrong_rank_is_rejected(shape):
    with pytest.raises(ValueError, match="batch, channels, time"):
        EMD()(torch.zeros(shape))
