"""Code parity: the sparse codes the exported graph computes, against scikit-learn's.

A model whose preprocessing holds :class:`~tactile.training.sparse.SparseCoder` modules (the
``sf_rnn`` and ``sparse_linear`` models: one coder per modality) has each coder traced into the
graph's ``post`` part as a sub-graph: the nodes whose scope is the coder's module (the
exporter names a node ``.../<scope>/<op>``, the scope being the coder's qualified name in the
model, or its tail). Its one input from outside the scope is the images ``(rows, features)``
(rows = windows x steps) and its one output used outside is the codes ``(rows, atoms)``.

To observe them, the file's own graph is copied with those two values added as outputs (the
nodes are the file's, unchanged: :mod:`tactile.export.taps`) and run by onnxruntime on the
parity windows. scikit-learn's
transform with the coder's dictionary (``sklearn.decomposition.SparseCoder(D,
transform_algorithm='omp', transform_n_nonzero_coefs=n)``, as ``MiniBatchDictionaryLearning``
transforms) codes the same images, and :func:`judge` measures (with
:func:`tactile.training.sparse_check.compare`): the same non-zero atoms on at least
:data:`AGREEMENT` of the rows, max |difference| at most :data:`RTOL` x the code's norm where
they agree, and every disagreement explained.

Real windows need a referee beside scikit-learn: both sides compute in float32, and on the
BioTac's images (near-silent vibration windows whose atom correlations are all alike;
electrode images whose five time steps are nearly equal, so their atoms are nearly collinear)
scikit-learn's float32 run itself leaves the float64 OMP path on a few rows in a thousand, and
its coefficients and the graph's on an ill-conditioned atom set are each only as accurate as
float32 least squares through the Gram matrix allows. So a row above :data:`RTOL` passes when
the graph's code is at least as close to float64 least squares as scikit-learn's, or within
float32's accuracy for its atoms, (cond(D_S)^2 + sqrt(features) + non-zeros) x epsilon
(:func:`float32_bound`), and a disagreement passes as a near-tie (where the graph's run
parted from scikit-learn's, reconstructed from the correlations its transform computed), as
the float64 OMP's choice, or as a code whose residual is no larger than scikit-learn's
(:func:`judge`); each count is reported.
"""

from __future__ import annotations

import warnings

import numpy as np
import onnx
from torch import nn

from tactile.export.taps import CoderNotFound, find_coders, graph_order, tap_session
from tactile.training.sparse import EPS as FLOAT32_EPS

AGREEMENT = 0.99
"""Least share of rows whose non-zero atoms equal scikit-learn's."""
RTOL = 1e-4
"""Largest max |code - scikit-learn's| / ||scikit-learn's code|| where the atoms agree."""
TIE = 1e-4
"""A disagreement is excused when scikit-learn's pick and the graph's are this close (float64
residual correlations, relative to the largest): float32 rounding may decide it either way."""
RESOLUTION_FACTOR = 4.0
"""A flip is a near-tie when its gap is below this many times float32's resolution of the
step's correlations (:func:`~tactile.training.sparse_check.divergence`), if that exceeds
:data:`~tactile.export.codes.TIE`: one float32 run's correlation errors reached 2.04 x the
resolution (median 0.51; ``tests/test_sparse.py``), and a flip's gap holds two runs' errors."""
MAX_ROWS = 8192
"""At most this many rows (a seeded sample) per coder go to scikit-learn."""


def sklearn_codes(dictionary: np.ndarray, n_nonzero: int, x: np.ndarray) -> np.ndarray:
    """scikit-learn's transform of ``x`` (rows, features) float32 with ``dictionary``."""
    from sklearn.decomposition import SparseCoder as SkSparseCoder

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Orthogonal matching pursuit ended prematurely"
        return SkSparseCoder(dictionary, transform_algorithm="omp",
                             transform_n_nonzero_coefs=n_nonzero).transform(x)


def omp64(d: np.ndarray, x: np.ndarray, n: int) -> np.ndarray:
    """The referee: scikit-learn's OMP of one window ``x`` (features,) in float64."""
    from sklearn.linear_model import orthogonal_mp_gram

    d64, x64 = d.astype(np.float64), x.astype(np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return orthogonal_mp_gram(d64 @ d64.T, d64 @ x64, n_nonzero_coefs=n)


def _lstsq_error(d: np.ndarray, x: np.ndarray, code: np.ndarray) -> float:
    """max |code - float64 least squares on code's atoms| / its norm."""
    sup = np.flatnonzero(code)
    c64 = np.linalg.lstsq(d[sup].astype(np.float64).T, x.astype(np.float64), rcond=None)[0]
    return float(np.abs(code[sup] - c64).max() / max(np.linalg.norm(c64), 1e-30))


def float32_bound(d: np.ndarray, code: np.ndarray) -> float:
    """Float32's accuracy for a code on atoms S, relative to its norm: (cond(D_S)^2 + sqrt(F) + s)
    x float32's epsilon, D_S the code's s atoms (features F, s). Least squares solved through
    the Gram matrix D_S^T D_S (as OMP solves it, in scikit-learn and here) loses cond(D_S)^2 x
    epsilon; sqrt(F) + s is the rounding any code takes, however well its atoms are conditioned:
    its F-term correlations (rounding errors adding up as random ones do) and its s
    orthogonalisation steps. An estimate, not a guarantee (``tests/test_export_ties.py`` checks
    PyTorch's and onnxruntime's codes against float64 least squares on the same atoms). Two
    float32 codes of one image on the same atoms are held to twice it
    (:func:`float32_apart`). 0 for an empty code."""
    sup = np.flatnonzero(code)
    if not len(sup):
        return 0.0
    cond = float(np.linalg.cond(d[sup].astype(np.float64)))
    return (cond * cond + float(np.sqrt(d.shape[1])) + len(sup)) * FLOAT32_EPS


def rel_diff(got: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per row of codes (rows, atoms): max |got - ref| / ||ref|| (0 where both are zero)."""
    diff = np.abs(got.astype(np.float64) - ref).max(1)
    norm = np.linalg.norm(ref.astype(np.float64), axis=1)
    return np.where(diff == 0, 0.0, diff / np.maximum(norm, 1e-30))


def float32_apart(d: np.ndarray, got: np.ndarray, ref: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Two float32 codes of the same images on the same atoms (rows, atoms), dictionary ``d``:
    per row their :func:`rel_diff` and its tolerance, twice :func:`float32_bound` of ``ref``
    (each code within float32's accuracy of the exact one)."""
    return rel_diff(got, ref), np.array([2 * float32_bound(d, c) for c in ref])


def _residual(d: np.ndarray, x: np.ndarray, code: np.ndarray) -> float:
    """||x - D^T code|| in float64."""
    return float(np.linalg.norm(x.astype(np.float64) - d.astype(np.float64).T @ code))


def parting(d: np.ndarray, x: np.ndarray, first: list[int], second: list[int]
            ) -> tuple[float, float]:
    """Where two OMP runs of image ``x`` with selection orders ``first`` and ``second`` (-1
    after a stop) parted: ``(gap, tolerance)``, their picks' float64 residual correlations'
    gap after the atoms both picked before (:func:`~tactile.training.sparse_check.divergence`)
    and the near-tie tolerance, :data:`TIE` of the largest or :data:`RESOLUTION_FACTOR` x
    float32's resolution of that step's correlations, whichever is larger."""
    from tactile.training.sparse_check import divergence

    gap, resolution = divergence(d, x, first, second)
    return gap, max(TIE, RESOLUTION_FACTOR * resolution)


def near_tie(d: np.ndarray, x: np.ndarray, first: list[int], second: list[int]) -> bool:
    """True when two OMP runs parted at a near-tie (:func:`parting`: |gap| < tolerance)."""
    gap, tolerance = parting(d, x, first, second)
    return abs(gap) < tolerance


def judge(ref: np.ndarray, got: np.ndarray, d: np.ndarray, x: np.ndarray, n: int,
          order: np.ndarray | None = None) -> dict:
    """The graph's codes ``got`` against scikit-learn's ``ref`` (rows, atoms) of images ``x``
    (rows, features), dictionary ``d`` (atoms, features), ``n`` non-zeros.

    Rows with the same non-zero atoms: max |got - ref| / ||ref|| (``max_rel_diff``); a row
    above :data:`RTOL` is excused when the graph's code is at least as close to the float64
    least-squares code on those atoms as scikit-learn's is, or within float32's accuracy for
    them (:func:`float32_bound`): on ill-conditioned atom sets of real windows both float32
    codes stray from float64 by up to ~1e-3 x the norm, and which of the two strays more is
    the rounding's draw. Rows with
    other atoms are explained, in this order, as a near-tie (:func:`tie_gap` below
    :data:`TIE` in magnitude, or, given the graph's selection ``order`` (rows, n; -1 after a
    stop), a :func:`near_tie` where scikit-learn's run and the graph's parted, which may lie
    before the first atom scikit-learn has and the graph lacks; scikit-learn's run is
    reconstructed from the correlations its transform computed for the batch,
    :func:`~tactile.training.sparse_check.correlations`), as the float64 OMP's own
    choice (the graph's atoms are those of :func:`omp64`: scikit-learn's float32 run left the
    float64 path), or as an equally good code (the graph's float64 residual at most
    scikit-learn's); anything else fails."""
    from tactile.training.sparse_check import compare

    stats = compare(ref, got, d, x, n)
    same = ((ref != 0) == (got != 0)).all(1)
    rel = rel_diff(got, ref)
    over = np.flatnonzero(same & (rel > RTOL))
    unexcused_over, worst_f64 = 0, 0.0
    for i in over:
        mine, theirs = _lstsq_error(d, x[i], got[i]), _lstsq_error(d, x[i], ref[i])
        worst_f64 = max(worst_f64, mine)
        unexcused_over += mine > max(theirs, RTOL, float32_bound(d, got[i]))
    why = {"tie": 0, "float64": 0, "residual": 0, "unexplained": 0}
    for i, gap, theirs in zip(np.flatnonzero(~same), stats["gaps"], stats["orders"]):
        if abs(gap) < TIE or (order is not None and near_tie(
                d, x[i], theirs, order[i].tolist())):
            why["tie"] += 1
        elif set(np.flatnonzero(omp64(d, x[i], n))) == set(np.flatnonzero(got[i])):
            why["float64"] += 1
        elif _residual(d, x[i], got[i]) <= _residual(d, x[i], ref[i]) * (1 + 1e-6):
            why["residual"] += 1
        else:
            why["unexplained"] += 1
    passed = stats["agree"] >= AGREEMENT and not unexcused_over and not why["unexplained"]
    return {"rows": stats["windows"], "same_atoms": stats["same"],
            "agreement": round(stats["agree"], 6), "max_rel_diff": float(f"{stats['max_rel']:.3g}"),
            "rows_over_rtol": len(over), "rows_over_rtol_unexcused": int(unexcused_over),
            "max_rel_f64_over_rtol": float(f"{worst_f64:.3g}"),
            "disagreements": int((~same).sum()), "explained": why, "passed": bool(passed)}


def code_parity(model: nn.Module, graph: onnx.ModelProto, windows: np.ndarray,
                max_rows: int = MAX_ROWS, seed: int = 0) -> list[dict]:
    """Per coder of ``model``: the graph's codes of ``windows`` (N, T, C) float32 (zero state)
    against scikit-learn's on the same images (:func:`judge`). One dict per coder: ``coder``
    (module path), ``name`` (its modality, when the model has a ``layout``), ``atoms``,
    ``features``, ``nonzero`` and :func:`judge`'s figures."""
    taps = find_coders(model, graph)
    if not taps:
        return []
    sess, steps, names = tap_session(graph, taps)
    layers, hidden = model.state_shape
    got: dict[str, list[np.ndarray]] = {v: [] for v in names}
    for i in range(0, len(windows), 256):
        xb = np.ascontiguousarray(windows[i : i + 256], np.float32)
        h = np.zeros((layers, len(xb), hidden), np.float32)
        outs = sess.run(names, {"x": xb, "h": h, "c": h})
        for v, o in zip(names, outs):
            got[v].append(o)
    layout = getattr(model, "layout", None)
    rng = np.random.default_rng(seed)
    report = []
    for k, t in enumerate(taps):
        x, codes = np.concatenate(got[t.x]), np.concatenate(got[t.codes])
        order = None if steps is None else graph_order(
            np.concatenate([np.concatenate(got[v]) for v in steps[k]], axis=1), codes)
        d = t.coder.dictionary.numpy()
        if x.ndim != 2 or x.shape[1] != d.shape[1] or codes.shape != (len(x), d.shape[0]):
            raise CoderNotFound(f"coder {t.path!r}: the graph's values {t.x!r} {x.shape} and "
                                f"{t.codes!r} {codes.shape} are not (rows, {d.shape[1]}) and "
                                f"(rows, {d.shape[0]})")
        if len(x) > max_rows:
            keep = np.sort(rng.choice(len(x), max_rows, replace=False))
            x, codes = x[keep], codes[keep]
            order = None if order is None else order[keep]
        n = t.coder.n_nonzero
        name = layout[k].name if layout is not None and len(layout) == len(taps) else t.path
        report.append({"coder": t.path, "name": name, "atoms": int(d.shape[0]),
                       "features": int(d.shape[1]), "nonzero": n,
                       **judge(sklearn_codes(d, n, x), codes, d, x, n, order)})
    return report


def table_rows(report: list[dict]) -> list[tuple[str, str]]:
    """Lines for the parity table: one per coder."""
    rows = []
    for r in report:
        e = r["explained"]
        why = ", ".join(f"{v} {k}" for k, v in e.items() if v)
        over = "" if not r["rows_over_rtol"] else (
            f", {r['rows_over_rtol']} above it as close to float64 as scikit-learn's or "
            "within float32's accuracy"
            if not r["rows_over_rtol_unexcused"] else
            f", {r['rows_over_rtol_unexcused']} above it unexplained")
        rows.append((f"codes {r['name']}",
                     f"{r['same_atoms']}/{r['rows']} rows same atoms as scikit-learn "
                     f"({r['agreement']:.4f}; others: {why or 'none'}), max |dc|/|c| "
                     f"{r['max_rel_diff']:.2g} (limit {RTOL:g}{over}); "
                     f"{'PASS' if r['passed'] else 'FAIL'}"))
    return rows
