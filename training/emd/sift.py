"""One sift: subtract the mean of the upper and lower envelopes (EMD_SPEC §1.3, §4.1-4.8).

A sift is three stages, so that the exported graph can put the spline solve's later steps in
``If`` nodes: :func:`prepare` (extrema to the spline system), :func:`spline.solve` (PCR),
and :func:`finish` (envelopes and the update). Large batches lay some tensors out differently
(``large``), with the same arithmetic: a row's result does not depend on the batch.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .boundary import boundary_knots, side_coordinates
from .envelope import evaluate, segment_index
from .extrema import extrema_marks
from .knots import assemble, end_extrema, end_extrema_topk, extrema_counts, past_dummies
from .spline import large_path, solve, spacings, spline_system


def prepare(
    h: Tensor,
    marks: Tensor,
    base: tuple[Tensor, Tensor, Tensor, Tensor] | None = None,
    ends: Tensor | None = None,
    large: bool | None = None,
) -> tuple[Tensor, ...]:
    """Knots and spline system of both envelopes of every row.

    Args:
        h: (R, N) signals, N >= 3, finite; marks: (2, R, N) their extremum marks.
        base, ends: :func:`knots.slot_base` and :func:`knots.end_base` of ``h`` (computed
            when not given).
        large: the path for many rows: the end extrema by running count
            (:func:`knots.end_extrema`, where onnxruntime's ``TopK`` is the slower) and the
            boundary rule with the row axis last (:func:`boundary.boundary_knots`); otherwise
            :func:`knots.end_extrema_topk` and the row-first layout. The same knots either way.
            By default from :data:`spline.LARGE_ROWS` rows on, as the exported graph chooses.

    Returns:
        sys: (3, 2, R, K) the unit-diagonal system (:func:`spline.spline_system`).
        xy: (2, 2, R, K) knots; j1: (2, R, 1) last real slot; ks: (2, R, N) slot of the last
        knot counted at each sample (:func:`knots.assemble`); n_ext: (R, 1) extrema per row
        (PyEMD's ``extNo``); hk, sl: (1, 2, R, K) knot spacings and secant slopes
        (:func:`spline.spacings`).
    """
    if large is None:
        large = large_path(int(h.shape[0]))
    if large:
        cnt, n = extrema_counts(marks)  # (2, R, N), (2, R, 1, 1)
        p, v = end_extrema(h, cnt, n)  # (2, R, 2, 4) x2
        last = (0, 2, 3, 1)  # (2, R, a, b) -> (2, a, b, R)
        q = side_coordinates(p.permute(last), int(h.shape[-1]), rows_last=True)
        bxy, bv = boundary_knots(h, q, v.permute(last), n.permute(last), rows_last=True)
        bxy, bv = bxy.transpose(-1, -2), bv.transpose(-1, -2)
    else:
        q, v, n = end_extrema_topk(h, marks, ends)  # (2, R, 2, 4) x2, (2, R, 1, 1)
        bxy, bv = boundary_knots(h, q, v, n)  # (2, 2, R, 4), (2, R, 4)
    # (2, 2, R, K) knots (half values), (2, R, 1) last slot, (2, R, N) slot at each sample:
    xy, j1, ks = assemble(h, marks, bxy, bv, base)
    hk, sl = spacings(xy, past_dummies(int(h.shape[-1])))  # for the system and the envelopes
    return spline_system(xy, j1, hk, sl), xy, j1, ks, n.sum(dim=(0, 3)), hk, sl


def finish(
    h: Tensor, active: Tensor, xy: Tensor, m: Tensor, j1: Tensor, ks: Tensor, n_ext: Tensor,
    hk: Tensor, sl: Tensor, large: bool | None = None,
) -> tuple[Tensor, Tensor]:
    """Evaluate the envelopes and subtract their mean (the arguments as :func:`prepare` gives
    them, ``m`` (1, 2, R, K) from :func:`spline.solve`); returns as :func:`sift`.

    ``large`` (by default from :data:`spline.LARGE_ROWS` rows on, as in :func:`prepare`) adds
    the two half envelopes as two tensors instead of reducing over their axis: the same single
    addition, so the same bits. onnxruntime's reduction over a leading axis costs about 1 ns an
    element, seven times the split and the addition; with few rows the one reduction node is
    cheaper.
    """
    if large is None:
        large = large_path(int(h.shape[0]))
    half = evaluate(h, xy, m, segment_index(ks, j1), hk, sl)  # (1, 2, R, N) envelopes / 2
    active = active & (n_ext > 2.0)  # (R, 1)
    if large:
        upper, lower = half.split(1, dim=1)  # (1, 1, R, N) each
        mean = (upper + lower).squeeze(1).squeeze(0)
    else:
        mean = half.sum(dim=(0, 1))  # (R, N): (upper + lower) / 2, bit for bit as PyEMD's
    return torch.where(active, h - mean, h), active


def envelopes(h: Tensor, marks: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Upper and lower envelopes of each row, as PyEMD's cubic-spline envelopes.

    Args:
        h: (R, N) signals, N >= 3, finite.
        marks: (2, R, N) extremum marks of ``h`` (:func:`extrema.extrema_marks`), computed
            here when not given.

    Returns:
        env: (2, R, N) [upper, lower]; meaningless in rows with fewer than 3 extrema.
        n_ext: (R, 1) number of extrema (PyEMD's ``extNo``).
    """
    if marks is None:
        marks = extrema_marks(h)  # (2, R, N)
    sys, xy, j1, ks, n_ext, hk, sl = prepare(h, marks)
    m = solve(sys, j1)
    return evaluate(h, xy, m, segment_index(ks, j1), hk, sl)[0] * 2.0, n_ext


def sift(h: Tensor, active: Tensor, marks: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """One sift of every active row; rows with fewer than 3 extrema become inactive.

    Args:
        h: (R, N) current proto-IMFs.
        active: (R, 1) bool, rows still being sifted (a column: it selects rows of ``h``).
        marks: (2, R, N) extremum marks of ``h``, computed here when not given (the exported
            graph computes them in an ``If`` before the rest of the sift).

    Returns:
        h: (R, N) ``h - (upper + lower) / 2`` where active, unchanged elsewhere.
        active: (R, 1) ``active`` and the row had more than 2 extrema (PyEMD stops the whole
            decomposition of a row the first time a sift finds ``extNo <= 2``).
    """
    if marks is None:
        marks = extrema_marks(h)  # (2, R, N)
    sys, xy, j1, ks, n_ext, hk, sl = prepare(h, marks)
    return finish(h, active, xy, solve(sys, j1), j1, ks, n_ext, hk, sl)
