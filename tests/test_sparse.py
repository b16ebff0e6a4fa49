"""SparseCoder against scikit-learn's default transform (OMP), in torch and in onnxruntime.

The reference is scikit-learn itself: ``MiniBatchDictionaryLearning.transform`` for dictionaries
it learned, ``sklearn.decomposition.SparseCoder(..., transform_algorithm='omp')`` for random
unit-norm ones, both on held-out float32 windows. Over the grid atoms x features x non-zeros:

* the same non-zero atoms on >= 99 % of windows (:data:`MIN_AGREEMENT`);
* where they agree, max |code - reference| <= 1e-4 x ||reference code|| (:data:`REL_TOL`);
* every disagreement is a near-tie: at the first atom of scikit-learn's selection order that
  the other code lacks, the float64 residual correlations (after the atoms chosen before it)
  of that atom and of the best atom the other code chose instead differ by less than
  :data:`TIE` x the largest correlation. Float32 rounding decides such ties either way.
"""

from __future__ import annotations

import collections
import warnings

import numpy as np
import onnxruntime as ort
import pytest
import torch
from sklearn.decomposition import MiniBatchDictionaryLearning
from sklearn.decomposition import SparseCoder as SkSparseCoder

from tactile.errors import ConfigError
from tactile.export.coder_graph import coder_graph
from tactile.training.sparse import SparseCoder, default_n_nonzero
from tactile.training.sparse_check import compare, sklearn_order, structured, tie_gap

ATOMS = (20, 100, 200)
FEATURES = (25, 110, 176)
NONZEROS = (1, 3, 5, 10)
WINDOWS = 300  # held-out windows per dictionary
MIN_AGREEMENT = 0.99
REL_TOL = 1e-4
TIE = 1e-4  # relative gap of the top two float64 correlations that float32 may decide wrongly
OPSET = 18
# Nodes of the exported coder (opset 18, constant-folded), per non-zero count; the graph is
# the same for every dictionary size: 27 for 1 non-zero, 77 for 2, then 52 per further OMP
# step (argmax, one-hot, 3 GatherElements and 7 Gather, the Cholesky row as a MatMul, the
# projections, the masks, the residual update); the first step has no Cholesky row and no
# already-chosen or pivot test.
NODE_BUDGET = {1: 27, 3: 129, 10: 493, 17: 857}
ALLOWED_OPS = {
    "MatMul", "ArgMax", "Abs", "Gather", "GatherElements", "Equal", "Cast", "Mul", "Sub", "Add",
    "Div", "Sqrt", "Where", "Greater", "GreaterOrEqual", "And", "Concat", "Unsqueeze",
    "Squeeze", "Transpose", "Shape", "ConstantOfShape", "Slice", "ReduceSum", "Constant",
}


@pytest.fixture(scope="module")
def cases() -> dict:
    """{(kind, atoms, features): (dictionary, held-out windows, reference(n) -> codes)}."""
    out = {}
    for k in ATOMS:
        for f in FEATURES:
            x_test = structured(WINDOWS, f, seed=1000 + f)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # convergence notes of a one-epoch fit
                learned = MiniBatchDictionaryLearning(
                    n_components=k, batch_size=64, max_iter=1, random_state=0,
                ).fit(structured(600, f, seed=f))
            assert learned.transform_algorithm == "omp"  # the default this coder reproduces

            def ref_learned(n, m=learned, x=x_test):
                return m.set_params(transform_n_nonzero_coefs=n).transform(x)

            rnd = np.random.default_rng(k * 1000 + f).standard_normal((k, f))
            rnd /= np.linalg.norm(rnd, axis=1, keepdims=True)

            def ref_random(n, d=rnd, x=x_test):
                return SkSparseCoder(d, transform_algorithm="omp",
                                     transform_n_nonzero_coefs=n).transform(x)

            out[("learned", k, f)] = (learned.components_, x_test, ref_learned)
            out[("random", k, f)] = (rnd, x_test, ref_random)
    return out


def session(model) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    return ort.InferenceSession(model.SerializeToString(), so,
                                providers=["CPUExecutionProvider"])


def check(stats: dict, where: str) -> None:
    assert stats["agree"] >= MIN_AGREEMENT, (where, stats)
    assert stats["max_rel"] <= REL_TOL, (where, stats)
    assert all(0 <= g < TIE for g in stats["gaps"]), (where, stats["gaps"])


@pytest.mark.parametrize("kind", ["learned", "random"])
def test_torch_matches_sklearn_over_the_grid(cases, kind):
    worst = collections.defaultdict(float)
    disagreements = 0
    for k in ATOMS:
        for f in FEATURES:
            d, x, ref_of = cases[(kind, k, f)]
            for n in NONZEROS:
                ref = ref_of(n)
                with torch.no_grad():
                    got = SparseCoder(d, n)(torch.from_numpy(x)).numpy()
                assert got.shape == ref.shape == (WINDOWS, k) and got.dtype == np.float32
                assert ((got != 0).sum(1) <= n).all()
                stats = compare(ref, got, d, x, n)
                check(stats, (kind, k, f, n))
                worst["max_rel"] = max(worst["max_rel"], stats["max_rel"])
                disagreements += len(stats["gaps"])
    # float32 rounding of both sides, growing with the conditioning of the chosen atoms (the
    # worst cell, 20 learned atoms of 25 features with 10 non-zeros, has cond ~2e3 and ~7e-5);
    # near-ties decided the other way are rare over the grid's 7,200 windows
    assert worst["max_rel"] <= REL_TOL, worst
    assert disagreements <= 5, disagreements


@pytest.mark.parametrize("kind", ["learned", "random"])
def test_onnxruntime_matches_sklearn_over_the_grid(cases, kind):
    """The exported graph, run by onnxruntime (one thread): the whole grid for learned
    dictionaries, the largest non-zero count for random ones (export takes ~1 s a graph)."""
    nonzeros = NONZEROS if kind == "learned" else (10,)
    for k in ATOMS:
        for f in FEATURES:
            d, x, ref_of = cases[(kind, k, f)]
            for n in nonzeros:
                got = session(coder_graph(SparseCoder(d, n))).run(None, {"x": x})[0]
                assert got.shape == (WINDOWS, k) and got.dtype == np.float32
                check(compare(ref_of(n), got, d, x, n), (kind, k, f, n))


def test_the_tie_explanation_accepts_a_tie_and_rejects_a_wrong_atom():
    """The grid has no disagreement; this checks that the explanation it would apply tells a
    tie (two atoms equally correlated with the window) from a code that took a wrong atom."""
    rng = np.random.default_rng(7)
    d = rng.standard_normal((30, 12))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = (d[2] + d[5]).astype(np.float32)  # <d2, x> = <d5, x> = 1 + <d2, d5>: an exact tie
    first = sklearn_order(d, x, 1)
    assert first in ([2], [5])
    other = 7 - first[0]  # the tied atom scikit-learn did not take
    assert 0 <= tie_gap(d, x, first, {other}) < 1e-6
    wrong = int(np.argmin(np.abs(d @ x)))  # the atom least correlated with x
    assert tie_gap(d, x, first, {wrong}) > 0.1


def test_default_non_zeros_are_sklearns():
    """``transform_n_nonzero_coefs=None``: int(features / 10), at least 1, at most atoms; the
    paper's sizes give 17 (vibration, 176 features), 2 (pressure, 25), 9 (electrodes, 95)."""
    assert [default_n_nonzero(f, k) for f, k in ((176, 200), (25, 100), (95, 100))] == [17, 2, 9]
    assert default_n_nonzero(5, 100) == 1 and default_n_nonzero(300, 20) == 20
    rng = np.random.default_rng(3)
    d = rng.standard_normal((100, 95))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = structured(200, 95, seed=4)
    ref = SkSparseCoder(d).transform(x)  # every default: omp, n_nonzero None
    assert (ref != 0).sum(1).max() == 9
    with torch.no_grad():
        got = SparseCoder(d, default_n_nonzero(95, 100))(torch.from_numpy(x)).numpy()
    check(compare(ref, got, d, x, 9), "default")


def codes_of(impl: str, d: np.ndarray, n: int, x: np.ndarray) -> np.ndarray:
    """Codes (windows, atoms) of float32 windows ``x`` by ``SparseCoder(d, n)`` in torch or in
    onnxruntime."""
    coder = SparseCoder(d, n)
    if impl == "torch":
        with torch.no_grad():
            return coder(torch.from_numpy(x)).numpy()
    return session(coder_graph(coder)).run(None, {"x": x})[0]


def sk_codes(d: np.ndarray, n: int, x: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scikit-learn warns "ended prematurely"
        return SkSparseCoder(d, transform_algorithm="omp", transform_n_nonzero_coefs=n) \
            .transform(x)


@pytest.mark.parametrize("impl", ["torch", "onnxruntime"])
def test_early_exits_are_masked_like_sklearns(impl):
    """scikit-learn stops a row early when the residual's best correlation is (nearly) zero or
    is an atom already chosen (and when a new atom depends linearly on the chosen ones, which
    rounding alone reaches: not provoked here); the graph masks the remaining steps instead,
    with the same codes."""
    rng = np.random.default_rng(5)
    d = rng.standard_normal((30, 12))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = np.stack([
        2 * d[3] - d[7],  # exactly two atoms: the residual vanishes after two steps
        np.zeros(12),  # nothing to code
        rng.standard_normal(12),  # generic: all 6 steps
    ]).astype(np.float32)
    got, ref = codes_of(impl, d, 6, x), sk_codes(d, 6, x)
    assert ((ref != 0) == (got != 0)).all()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5)
    assert sorted(np.flatnonzero(got[0])) == [3, 7]
    assert (got[1] == 0).all() and (got[2] != 0).sum() == 6
    if impl == "torch":  # the order output: -1 after the row stopped
        with torch.no_grad():
            order = SparseCoder(d, 6).encode(torch.from_numpy(x))[1].numpy()
        assert sorted(order[0][:2]) == [3, 7] and (order[0][2:] == -1).all()
        assert (order[1] == -1).all() and (order[2] >= 0).all()
    # more non-zeros than features: the residual vanishes after 12 atoms, so the row stops
    got20, ref20 = codes_of(impl, d, 20, x[2:]), sk_codes(d, 20, x[2:])
    assert (got20 != 0).sum() == (ref20 != 0).sum() == 12
    assert ((got20 != 0) == (ref20 != 0)).all()
    np.testing.assert_allclose(got20, ref20, rtol=0, atol=REL_TOL * np.linalg.norm(ref20))


@pytest.mark.parametrize("impl", ["torch", "onnxruntime"])
def test_an_atom_of_tiny_norm_is_taken_first_and_refused_later_like_sklearns(impl):
    """scikit-learn tests the Cholesky pivot (the atom's squared norm left after the chosen
    ones) from the second step on only: an atom of norm 1e-4 (squared norm 1e-8, below float32's
    epsilon) is taken at the first step, with coefficient <d0, x> / ||d0||^2 = 1e-2 / 1e-8 =
    1e6, but refused after another atom (the row stops there)."""
    d = np.eye(4)
    d[0] *= 1e-4
    x = np.array([[100, 0, 0, 0],  # atom 0 first: 1e6
                  [100, 5, 0, 0]],  # atom 1 first (correlation 5 > 1e-2), then atom 0 refused
                 np.float32)
    got, ref = codes_of(impl, d, 2, x), sk_codes(d, 2, x)
    np.testing.assert_allclose(ref, [[1e6, 0, 0, 0], [0, 5, 0, 0]], rtol=1e-6)  # hand-computed
    assert ((ref != 0) == (got != 0)).all()
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=0)


def test_exported_graph_contract_and_node_budget():
    """Opset 18, standard ops only (no NonZero, Loop or If: every row runs the same nodes),
    the dictionary as constants (the only input is x), a dynamic batch axis, and a node
    count that grows with the non-zero count only."""
    rng = np.random.default_rng(6)
    counts = {}
    for n, (k, f) in ((1, (100, 25)), (3, (20, 110)), (10, (200, 176)), (17, (200, 176))):
        d = rng.standard_normal((k, f))
        model = coder_graph(SparseCoder(d, n))
        assert [o.version for o in model.opset_import if o.domain in ("", "ai.onnx")] == [OPSET]
        ops = {node.op_type for node in model.graph.node}
        assert ops <= ALLOWED_OPS, ops - ALLOWED_OPS
        assert [i.name for i in model.graph.input] == ["x"]
        assert [o.name for o in model.graph.output] == ["codes"]
        counts[n] = len(model.graph.node)
        sess = session(model)
        for batch in (1, 7):
            x = rng.standard_normal((batch, f)).astype(np.float32)
            assert sess.run(None, {"x": x})[0].shape == (batch, k)
    over = {n: (counts[n], NODE_BUDGET[n]) for n in counts if counts[n] > NODE_BUDGET[n]}
    assert not over, f"node count over budget (got, budget): {over}"


def test_bad_settings_are_config_errors():
    d = np.eye(4)
    for bad, match in (((np.zeros(4), 1), "must be \\(atoms, features\\)"),
                       ((np.full((3, 2), np.nan), 1), "NaN or inf"),
                       ((d, 0), "n_nonzero 0: must be an integer in 1..4"),
                       ((d, 5), "n_nonzero 5"), ((d, True), "n_nonzero True"),
                       ((d, 2.0), "n_nonzero 2.0")):
        with pytest.raises(ConfigError, match=match):
            SparseCoder(*bad)


def test_a_fortran_ordered_dictionary_is_copied_into_c_order():
    """scikit-learn's ``components_`` may be Fortran-ordered. The coder owns a C-ordered copy:
    the layout a checkpoint restores, so the codes do not depend on how the dictionary came.
    (A Fortran-ordered buffer takes other matmul kernels: at batch 1 the correlations of this
    window with this dictionary differed in the last bits on 172 of 200 atoms, and 16 of the 17
    code values, when the coder kept the layout.)"""
    rng = np.random.default_rng(8)
    d = rng.standard_normal((200, 176)).astype(np.float32)
    f = np.asfortranarray(d)
    coder, ref = SparseCoder(f, 17), SparseCoder(d, 17)
    assert coder.dictionary.is_contiguous() and coder.gram.is_contiguous()
    assert coder.dictionary.stride() == ref.dictionary.stride() == (176, 1)
    assert torch.equal(coder.dictionary, ref.dictionary) and torch.equal(coder.gram, ref.gram)
    f[0, 0] += 1.0  # a copy of its own: the caller's array may change afterwards
    assert coder.dictionary[0, 0].item() == d[0, 0]
    x = torch.from_numpy(rng.standard_normal((1, 176)).astype(np.float32))
    with torch.no_grad():
        assert torch.equal(coder(x), ref(x))
        loaded = SparseCoder(np.zeros((200, 176), np.float32), 17)
        loaded.load_state_dict(coder.state_dict())  # what a checkpoint gives
        assert torch.equal(loaded(x), coder(x))


def test_float32_resolution_of_a_steps_correlations():
    """``divergence``'s resolution, eps32 x cond(D_P) x max |D x| / max |D r|, is the scale of
    float32's error in an OMP step's residual correlations (computed as OMP computes them,
    D x minus the Gram columns of the chosen atoms times their float32 least-squares
    coefficients) against float64, relative to the largest correlation: over 150 windows
    of 17 atoms plus noise from 1e-4 to 1e-1 of their level, at loudness 0.1 .. 1000, and all
    16 prefixes (2,399 steps before a row stopped), the error is about half the resolution
    (median 0.51) and 2.04 x it at most (the near-tie tolerance of the parity check is 4 x the
    resolution: a flip's gap holds two runs' errors)."""
    from tactile.training.sparse_check import FLOAT32_EPS, divergence

    rng = np.random.default_rng(0)
    d = rng.standard_normal((200, 176))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d32 = d.astype(np.float32)
    g32 = (d @ d.T).astype(np.float32)
    coder = SparseCoder(d32, 17)
    ratios = []
    for _ in range(150):
        loud = 10 ** rng.uniform(-1, 3)
        x = loud * (rng.standard_normal(17) @ d32[rng.choice(200, 17, replace=False)])
        x = (x + loud * 10 ** rng.uniform(-4, -1) * rng.standard_normal(176)).astype(np.float32)
        with torch.no_grad():
            order = coder.encode(torch.from_numpy(x[None]))[1][0].tolist()
        cov32, x64 = d32 @ x, x.astype(np.float64)
        for s in range(1, 17):
            p = order[:s]
            if order[s] < 0:  # the row stopped (its residual vanished)
                break
            c32 = np.linalg.solve(g32[np.ix_(p, p)], cov32[p]).astype(np.float32)
            a32 = cov32 - g32[:, p] @ c32  # float32 throughout
            r64 = x64 - d[p].T @ np.linalg.lstsq(d[p].T, x64, rcond=None)[0]
            a64 = np.abs(d @ r64)
            err = np.abs(np.abs(a32) - a64).max() / a64.max()
            # the resolution at step s: two orders parting there
            other = next(a for a in range(200) if a not in order[: s + 1])
            _, res = divergence(d, x, order[: s + 1], order[:s] + [other])
            expected = FLOAT32_EPS * np.linalg.cond(d[p].T) * np.abs(d @ x64).max() / a64.max()
            assert res == pytest.approx(expected, rel=1e-9)
            ratios.append(err / res)
    ratios = np.array(ratios)
    assert 0.2 <= np.median(ratios) <= 1.0 and ratios.max() <= 2.5, (np.median(ratios),
                                                                      ratios.max())
