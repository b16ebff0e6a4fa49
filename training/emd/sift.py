"""One sift: subtract the mean of the upper and lower envelopes (EMD_SPEC §1.3, §4.1-4.8).

A sift is three stages, so that the exported graph can run the spline solve's later steps in
a ``Loop``: :func:`prepare` (extrema to the spline system), :func:`spline.solve` (PCR),
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
from .spline import knot_width, large_path, pick, solve, spacings, spline_system


def prepare_knots(
    h: Tensor,
    marks: Tensor,
    base: tuple[Tensor, Tensor, Tensor, Tensor] | None = None,
    ends: Tensor | None = None,
    large: bool | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Knots of both envelopes of every row, and the knot width the rest of the sift needs.

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
        xy: (2, 2, R, K) knots (half values); j1: (2, R, 1) last real slot; ks: (2, R, N) slot
        of the last knot counted at each sample (:func:`knots.assemble`); n_ext: (R, 1) extrema
        per row (PyEMD's ``extNo``); width: (1,) int64 :func:`spline.knot_width`.
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
    return xy, j1, ks, n.sum(dim=(0, 3)), knot_width(j1, int(xy.shape[-1]))


def prepare_system(
    xy: Tensor, j1: Tensor, n_time: int, rows: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Spline system of knots cut to their :func:`spline.knot_width`.

    Args:
        xy: (2, 2, R, W) knots; j1: (2, R, 1) last real slot (``j1 <= W - 2``); n_time: N.
        rows: (2, W) :func:`spline.slot_rows` (the exported graph cuts them from a constant;
            made here when not given).

    Returns:
        sys: (3, 2, R, W) the unit-diagonal system (:func:`spline.spline_system`); hk, sl:
        (1, 2, R, W) knot spacings and secant slopes (:func:`spline.spacings`), which the
        envelopes use too.
    """
    hk, sl = spacings(xy, past_dummies(n_time))
    return spline_system(xy, j1, hk, sl, rows), hk, sl


def prepare(
    h: Tensor,
    marks: Tensor,
    base: tuple[Tensor, Tensor, Tensor, Tensor] | None = None,
    ends: Tensor | None = None,
    large: bool | None = None,
) -> tuple[Tensor, ...]:
    """Knots and spline system of both envelopes of every row (:func:`prepare_knots`, the cut
    to the knot width, :func:`prepare_system`; arguments as :func:`prepare_knots`).

    Returns:
        sys: (3, 2, R, W) the unit-diagonal system (:func:`spline.spline_system`).
        xy: (2, 2, R, W) knots; j1: (2, R, 1) last real slot; ks: (2, R, N) slot of the last
        knot counted at each sample (:func:`knots.assemble`); n_ext: (R, 1) extrema per row
        (PyEMD's ``extNo``); hk, sl: (1, 2, R, W) knot spacings and secant slopes
        (:func:`spline.spacings`). ``W``: :func:`spline.knot_width`.
    """
    xy, j1, ks, n_ext, width = prepare_knots(h, marks, base, ends, large)
    xy = xy[..., : int(width)]
    sys, hk, sl = prepare_system(xy, j1, int(h.shape[-1]))
    return sys, xy, j1, ks, n_ext, hk, sl


def finish(
    h: Tensor, active: Tensor, xy: Tensor, m: Tensor, j1: Tensor, ks: Tensor, n_ext: Tensor,
    hk: Tensor, sl: Tensor,
) -> tuple[Tensor, Tensor]:
    """Evaluate the envelopes and subtract their mean (the arguments as :func:`prepare` gives
    them, ``m`` (1, 2, R, K) from :func:`spline.solve`); returns as :func:`sift`.

    The two half envelopes are added as two tensors rather than by a reduction over their
    axis (the same single addition, so the same bits), in both layouts. onnxruntime's
    reduction over a leading axis is slow and has cliffs: on (1, 2, R, N) halves it took
    8.5 us against 7.2 us for a split and the addition at 1 x 1,100 (the halves are now taken
    with two Gathers, cheaper than the split), 51 us against 7.8 us at
    56 x 50, and was ahead (by 0.2 us) only at 8 x 50 (1.32, one thread).
    """
    half = evaluate(h, xy, m, segment_index(ks, j1), hk, sl)  # (1, 2, R, N) envelopes / 2
    active = active & (n_ext > 2.0)  # (R, 1)
    upper, lower = pick(half, 0, 1, dim=1)  # (1, 1, R, N) each
    mean = (upper + lower).reshape(-1, int(h.shape[-1]))  # (R, N): (upper + lower) / 2
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
            graph computes them, the plateau rule in a ``Loop`` of zero or one iteration,
            before the rest of the sift).

    Returns:
        h: (R, N) ``h - (upper + lower) / 2`` where active, unchanged elsewhere.
        active: (R, 1) ``active`` and the row had more than 2 extrema (PyEMD stops the whole
            decomposition of a row the first time a sift finds ``extNo <= 2``).
    """
    if marks is None:
        marks = extrema_marks(h)  # (2, R, N)
    sys, xy, j1, ks, n_ext, hk, sl = prepare(h, marks)
    return finish(h, active, xy, solve(sys, j1), j1, ks, n_ext, hk, sl)
