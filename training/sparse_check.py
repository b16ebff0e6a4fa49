"""Checking sparse codes against scikit-learn's OMP: agreement, and near-ties where they part.

Two codes of one window may choose different atoms when float32 rounding decides a near-tie.
:func:`compare` measures a batch of codes against scikit-learn's; for every window whose
non-zero atoms differ it gives :func:`tie_gap`: at the first atom of scikit-learn's selection
order (:func:`sklearn_order`) that the other code lacks, the float64 gap between that atom's
residual correlation and the best rival's, relative to the largest. A gap near zero is a tie;
a large one is a wrong atom. Used by ``tests/test_sparse.py`` and ``bench/sparse.py``, with
the windows of :func:`structured`.
"""

from __future__ import annotations

import warnings

import numpy as np
from sklearn.linear_model import orthogonal_mp_gram

from tactile.training.sparse import EPS as FLOAT32_EPS  # float32's epsilon


def sklearn_order(d: np.ndarray, x: np.ndarray, n: int,
                  gram: np.ndarray | None = None, xy: np.ndarray | None = None) -> list[int]:
    """The atoms scikit-learn's OMP picks for window ``x`` (features,) with dictionary ``d``
    (atoms, features) and ``n`` non-zeros, in order (from its coefficient path), computed as
    its transform computes them (Gram in x's dtype), or on ``gram`` when given. ``xy``: the
    correlations ``D x`` the transform started from (a column of :func:`correlations` of the
    batch it coded: one image's ``d @ x`` may round a tie otherwise); by default ``d @ x``."""
    if gram is None:
        gram = (d @ d.T).astype(x.dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "ended prematurely": an early exit is fine here
        path = orthogonal_mp_gram(gram, d @ x if xy is None else xy, n_nonzero_coefs=n,
                                  return_path=True)
    path = path.reshape(len(d), -1)
    order: list[int] = []
    for s in range(path.shape[1]):
        order += [int(a) for a in np.flatnonzero(path[:, s]) if a not in order]
    return order


def correlations(d: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(atoms, windows): the correlations of every window of the batch ``x`` (windows,
    features) with the atoms of ``d``, as scikit-learn's transform computes them for the batch
    it codes (one matrix product, ``np.dot(dictionary, X.T)``), the start of its OMP runs."""
    return np.dot(np.ascontiguousarray(d), np.ascontiguousarray(x).T)


def tie_gap(d: np.ndarray, x: np.ndarray, order: list[int], other: set[int]) -> float:
    """Relative gap, in float64, between scikit-learn's pick and the other code's best pick at
    the first step where scikit-learn picks an atom the other code lacks (inf if none).

    ``order`` is scikit-learn's selection order (:func:`sklearn_order`), ``other`` the other
    code's non-zero atoms; 0 <= gap < tolerance means a tie decided the other way."""
    d64, x64 = d.astype(np.float64), x.astype(np.float64)
    for s, atom in enumerate(order):
        if atom in other:
            continue
        chosen = order[:s]
        resid = x64
        if chosen:
            sub = d64[chosen]  # (s, F)
            resid = x64 - sub.T @ np.linalg.lstsq(sub.T, x64, rcond=None)[0]
        corr = np.abs(d64 @ resid)
        rivals = [c for c in other if c not in chosen]
        if not rivals:
            return float("inf")
        return float((corr[atom] - max(corr[c] for c in rivals)) / corr.max())
    # every atom scikit-learn chose is in the other code, which has more: scikit-learn stopped
    # early where the other did not
    return float("inf")


def divergence(d: np.ndarray, x: np.ndarray, first: list[int], second: list[int]
               ) -> tuple[float, float]:
    """Where two OMP runs parted: their selection orders ``first`` and ``second`` (-1: the run
    had stopped) of window ``x`` (features,) with dictionary ``d`` (atoms, features). Returns
    ``(gap, resolution)`` at the first step where they differ, in float64 after the atoms P both
    picked before it:

    * ``gap = (|c_a| - |c_b|) / max |c|``, the residual correlations c = D r of the two picks;
    * ``resolution = eps32 x cond(D_P) x max |D x| / max |c|``: the float32 error of that step's
      correlations relative to the largest. OMP computes them as ``D x`` minus what the chosen
      atoms explain, so float32's absolute error stays at the scale of ``D x`` (amplified by the
      conditioning of the chosen atoms) while the correlations shrink with the residual; after
      many atoms of a loud window float32 cannot order atoms whose correlations differ by less.

    ``(inf, 0)`` when one run stopped there, or when the orders never differ (over their
    common length). Unlike :func:`tie_gap`, which knows only the other code's atoms, this
    measures the decision where the two runs parted, even when their later steps brought them
    back to most of the same atoms."""
    for s, (a, b) in enumerate(zip(first, second)):
        if a == b:
            continue
        if a < 0 or b < 0:
            return float("inf"), 0.0
        d64, x64 = d.astype(np.float64), x.astype(np.float64)
        resid, cond = x64, 1.0
        if s:
            sub = d64[list(first[:s])].T  # (F, s)
            resid = x64 - sub @ np.linalg.lstsq(sub, x64, rcond=None)[0]
            cond = float(np.linalg.cond(sub))
        corr = np.abs(d64 @ resid)
        top = corr.max()
        if top == 0:  # nothing left to code: every atom ties
            return 0.0, 0.0
        return (float((corr[a] - corr[b]) / top),
                FLOAT32_EPS * cond * float(np.abs(d64 @ x64).max()) / top)
    return float("inf"), 0.0


def divergence_gap(d: np.ndarray, x: np.ndarray, first: list[int], second: list[int]) -> float:
    """The gap of :func:`divergence`."""
    return divergence(d, x, first, second)[0]


def compare(ref: np.ndarray, got: np.ndarray, d: np.ndarray, x: np.ndarray, n: int) -> dict:
    """Codes ``got`` against scikit-learn's ``ref`` (windows, atoms) for windows ``x``
    (windows, features), dictionary ``d`` and ``n`` non-zeros: ``same`` (windows with the same
    non-zero atoms, of ``windows``), ``agree`` (their share), ``max_rel`` (the largest
    max |ref - got| / ||ref|| over those windows), ``gaps`` (:func:`tie_gap` of every
    other window, in window order) and their scikit-learn ``orders`` (:func:`sklearn_order`
    from the batch's :func:`correlations`: ``ref`` is scikit-learn's transform of ``x`` as one
    batch)."""
    same = ((ref != 0) == (got != 0)).all(1)
    norm = np.linalg.norm(ref, axis=1)
    rel = np.abs(ref - got).max(1) / np.maximum(norm, 1e-30)
    differ = np.flatnonzero(~same)
    xy = correlations(d, x) if len(differ) else None
    orders = [sklearn_order(d, x[i], n, xy=xy[:, i]) for i in differ]
    gaps = [tie_gap(d, x[i], o, set(np.flatnonzero(got[i]))) for i, o in zip(differ, orders)]
    return {"same": int(same.sum()), "windows": len(same), "agree": float(same.mean()),
            "max_rel": float(rel[same].max()) if same.any() else 0.0, "gaps": gaps,
            "orders": orders}


def structured(n: int, features: int, seed: int) -> np.ndarray:
    """(n, features) float32 windows: a few of a pool of damped tones each, plus noise (so a
    dictionary has structure to learn and the windows are not all alike)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, features)
    m = 3 * features // 10 + 8
    freq, phase, decay = rng.uniform(0.5, features / 4, m), rng.uniform(0, 6.3, m), \
        rng.uniform(0, 5, m)
    pool = np.sin(2 * np.pi * freq[:, None] * t + phase[:, None]) * np.exp(-decay[:, None] * t)
    weights = rng.standard_normal((n, m)) * (rng.random((n, m)) < 4 / m)
    return (weights @ pool + 0.05 * rng.standard_normal((n, features))).astype(np.float32)


__all__ = ["compare", "correlations", "divergence", "divergence_gap", "sklearn_order",
           "structured", "tie_gap"]
