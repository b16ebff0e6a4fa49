"""Cubic-spline second derivatives for batches of knot sets, solved without a solver op.

PyEMD interpolates with ``scipy.interpolate.CubicSpline`` (not-a-knot) when an envelope has
more than 3 knots, and with a natural spline for exactly 3 (EMD_SPEC §1.6). With the real
knots in slots ``1 .. j1`` (slot 0 a placeholder, :mod:`knots`), spacings ``h`` and secant
slopes ``s``, the rows for the second derivatives ``M`` are

    h[j-1] M[j-1] + 2 (h[j-1] + h[j]) M[j] + h[j] M[j+1] = 6 (s[j] - s[j-1]),  1 < j < j1.

Not-a-knot eliminates ``M[1]`` into row 2 and ``M[j1]`` into row ``j1-1``; natural sets them
to 0. The rows are solved for ``M / 6``, which spares the factor 6. The eliminated system is
strictly diagonally dominant, so parallel cyclic reduction (PCR) without pivoting is stable:
each step couples every row to rows twice as far away, and ``ceil(log2 K)`` steps decouple all
rows. Rows outside ``2 .. j1-1`` are identity rows with right-hand side 0; ``M[1]`` and
``M[j1]`` are never needed because the envelope evaluates the outer segments with their
neighbour's cubic (not-a-knot: the same polynomial).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def pick(t: Tensor, *i: int, dim: int = 0) -> tuple[Tensor, ...]:
    """Single entries of ``t`` along ``dim``, each keeping the axis: ``index_select`` rather
    than ``split``, because onnxruntime gathers whole rows on a leading axis for less than a
    ``Split`` costs (about 0.4 against 1-2 us in a 1 x 1,100 sift, 1.32, one thread)."""
    return tuple(t.index_select(dim, torch.tensor([k], device=t.device)) for k in i)


def spacings(xy: Tensor, end: float | None = None) -> tuple[Tensor, Tensor]:
    """(2, ..., K) knot positions and values -> (1, ..., K) spacings ``x[j+1] - x[j]`` and secant
    slopes.

    The system and the envelopes' coefficients both use them (computed once a sift). Slot K-1
    is a placeholder: it pairs the last slot with the point ``(end, end)``, by default the last
    slot's position and value plus 1. ``end`` must lie above every position, so that this
    spacing is positive too; nothing real reads it (row K-1 of the system is an identity row,
    and no segment starts at slot K-1). After :func:`knots.slot_base`'s dummies,
    :func:`knots.past_dummies` makes it exactly 1, as the dummies' own spacings are. K wide
    rather than K-1, so that each shifted copy the system needs is one ``Pad``.
    """
    if end is None:
        nxt = torch.cat([xy[..., 1:], xy[..., -1:] + 1.0], dim=-1)
    else:
        nxt = F.pad(xy, (-1, 1), value=end)  # (2, ..., K): the next slot's [x, y]
    hk, dy = pick(nxt - xy, 0, 1)  # spacings (all > 0), rises
    return hk, dy / hk


def knot_width(j1: Tensor, k: int) -> Tensor:
    """(..., 1) last real knot slots -> (1,) int64: the slots the spline needs, ``max(j1) + 2``
    (never more than ``k``, the slots there are).

    The rest of a sift (spacings, system, PCR, envelope coefficients) works on the knots cut
    to this width: long windows have ``K = N // 2 + 6`` slots, but their later IMFs only a few
    knots (at 1,100 samples about 330, 155, 66, 20, 13, 9, 6 and 4 per envelope, IMF after
    IMF). The cut changes no bit of any row, whatever the other rows of the batch: the slots
    past a row's ``j1`` are identity rows of its system (solution 0, coupled to nothing), and
    PCR fills a shift past the edge with a zero row, which contributes the same zeros as an
    identity row would (:func:`_eliminate` never reads a neighbour's diagonal); the envelopes
    read slots up to ``j1`` only. Slot ``max(j1) + 1`` remains, a placeholder of
    :func:`spacings` above every real knot.
    """
    del k  # j1 <= K - 2 (knots.n_slots), so the width never exceeds K
    return (j1.reshape(-1).amax(0, keepdim=True) + 2.0).long()


def slot_rows(k: int, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """(2, K) what :func:`spline_system` needs of the slot numbers: 1 in row 2 (the left
    not-a-knot or natural row) and 0 elsewhere; each slot's number, with slots 0 and 1 placed
    at K, past every real knot. Made once for the exported graph and cut to the knot width."""
    j = torch.arange(k, dtype=dtype, device=device)
    return torch.stack([(j == 2.0).to(dtype), torch.where(j < 1.5, float(k), j)])


def spline_system(
    xy: Tensor, j1: Tensor, hk: Tensor | None = None, sl: Tensor | None = None,
    rows: Tensor | None = None,
) -> Tensor:
    """Tridiagonal rows for the knots' second derivatives over 6, each divided by its diagonal.

    Args:
        xy: (2, ..., K) knot positions (strictly increasing over all K slots) and values; the
            real knots are slots ``1 .. j1``.
        j1: (..., 1) last real knot slot (``j1 >= 3`` for real rows, ``j1 <= K - 2``).
        hk, sl: (1, ..., K) :func:`spacings` of ``xy``, computed here when not given.
        rows: (2, K) :func:`slot_rows` in ``xy``'s dtype, made here when not given (the
            exported graph passes them cut to the knot width, which varies with the batch).

    Returns:
        (3, ..., K): sub-diagonal, super-diagonal and right-hand side of the unit-diagonal rows
        whose solution is ``M / 6`` (the right-hand side is the slope change, without the 6).
    """
    k = int(xy.shape[-1])
    if rows is None:
        rows = slot_rows(k, xy.dtype, xy.device)
    row2, jpos = pick(rows, 0, 1)  # (1, K) each: row 2 (M[1] eliminated, or natural); slot numbers
    if hk is None or sl is None:
        hk, sl = spacings(xy)  # (1, ..., K) each
    hm = F.pad(hk, (1, -1), value=1.0)  # (1, ..., K): h[j-1]
    hp = hk  # (1, ..., K): h[j]; the placeholder in row K-1 is positive
    rhs = sl - F.pad(sl, (1, -1))  # (1, ..., K); rows 0, 1 and K-1 are masked
    # Distance from the last knot, with rows 0 and 1 placed past every real knot: negative
    # there, so one clamp masks both ends (and they are never taken for the right not-a-knot
    # row).
    dr = j1 - jpos  # (..., K)
    inner = torch.clamp(dr, 0.0, 1.0)  # rows 2 .. j1-1
    # Every row is [h[j-1], 2 s, h[j]] + w [-h[j], s, -h[j-1]] with s = h[j-1] + h[j]:
    # w = 0 inside and for the natural 3-knot row, w = h[j-1]/h[j] for the left not-a-knot row
    # and h[j]/h[j-1] for the right one, row j1-1 (EMD_SPEC §4.6, times h[j]/s or h[j-1]/s).
    # There the coefficient towards the eliminated knot vanishes up to rounding, and that knot's
    # identity row (M = 0, right-hand side 0) makes its value irrelevant.
    u = hm / hp
    w = torch.where(dr == 1.0, (1.0 - row2) / u, row2 * u)
    s = hm + hp
    a = hm - w * hp
    c = hp - w * hm
    return torch.cat([a, c, rhs]) * (inner / ((2.0 + w) * s))  # (3, ..., K)


def pcr_steps(k: int) -> int:
    """Number of PCR steps that decouple a K-row system."""
    return max(1, math.ceil(math.log2(k)))


def pcr_rows(sys: Tensor) -> Tensor:
    """(3, ..., K) unit-diagonal rows [sub-diagonal, super-diagonal, right-hand side] -> the
    (4, ..., K) rows :func:`pcr_step` takes: the diagonal itself (ones) appended, so that each
    step subtracts a row's own ``[r, 1]`` and normalises with one node each."""
    return F.pad(sys, (0, 0) * (sys.dim() - 1) + (0, 1), value=1.0)


_PICK_LO = (0, 4, 2, 1)  # a times [a, c, r, 1, 0] of row j - st -> [a a, 0, a r, a c]
_PICK_HI = (4, 1, 2, 0)  # c times [a, c, r, 1, 0] of row j + st -> [0, c c, c r, c a]
_OWN = (0.0, 0.0, 1.0, 1.0)  # what each new row subtracts of its own: [0, 0, r, 1]


def _eliminate(sys: Tensor, st: int) -> Tensor:
    """One PCR elimination of rows j -/+ st from every row j.

    Returns (4, ..., K): the new rows' unnormalised sub-diagonal, super-diagonal and
    right-hand side and the negated new diagonal, ``[a a_lo, c c_hi, a r_lo + c r_hi - r,
    a c_lo + c a_hi - 1]`` (``lo``/``hi``: row j -/+ st). Dividing by the negated diagonal folds
    the signs of the new off-diagonals in and turns the last row into the unit diagonal again.

    Each shifted copy is one ``Pad`` that also appends a zero row, so that one gather on the
    first axis lines the products up (onnxruntime gathers whole rows there for less than a
    ``Split`` or a ``Concat`` costs); the sums are those of the plain formulas, in their
    order, so the values are the same (a zero may change sign: ``x - 0 * a``), and the EMD's
    outputs the same bytes.
    """
    pads = (0, 0) * (sys.dim() - 2)
    lo = F.pad(sys, (st, -st) + pads + (0, 1))  # (5, ..., K): [a, c, r, 1, 0] of row j - st
    hi = F.pad(sys, (-st, st) + pads + (0, 1))  # (5, ..., K): the same of row j + st
    dev = sys.device
    a, c = (sys.index_select(0, torch.tensor([i], device=dev)) for i in (0, 1))  # (1, ..., K)
    pick_lo, pick_hi = (torch.tensor(p, device=dev) for p in (_PICK_LO, _PICK_HI))
    own = torch.tensor(_OWN, dtype=sys.dtype, device=dev).reshape(4, *[1] * (sys.dim() - 1))
    return (a * lo).index_select(0, pick_lo) + (c * hi).index_select(0, pick_hi) - sys * own


def pcr_step(sys: Tensor, st: int) -> Tensor:
    """One PCR step: couple every row to the rows ``2 st`` away instead of ``st``.

    Args:
        sys: (4, ..., K) unit-diagonal rows [sub-diagonal, super-diagonal, right-hand side,
            diagonal (1)] (:func:`pcr_rows`), coupling row j to rows j -/+ st.

    Returns:
        (4, ..., K) the same kind of rows, coupling row j to rows j -/+ 2 st.
    """
    rows = _eliminate(sys, st)
    return rows / rows.index_select(0, torch.tensor([3], device=sys.device))


def pcr_last(sys: Tensor, st: int) -> Tensor:
    """The final PCR step, computing only the solution: (4, ..., K) -> (1, ..., K)."""
    rows = _eliminate(sys, st)
    r, neg_diag = (rows.index_select(0, torch.tensor([i], device=sys.device)) for i in (2, 3))
    return r / neg_diag


def decoupled_after(j1: Tensor, steps: int) -> Tensor:
    """True (0-d bool) when ``steps`` PCR steps leave every real row of every system decoupled.

    After ``s`` steps row j couples to rows j -/+ 2^s; the real rows are 2 .. j1-1 and every
    other row is an identity row with solution 0, so once ``2^s >= j1 - 2`` for all systems the
    right-hand side is the solution, and further steps would leave it bit for bit unchanged.
    """
    return j1.amax() <= float((1 << steps) + 2)  # j1 holds whole numbers: exact


def more_steps(width: Tensor, first: int, steps: int) -> Tensor:
    """How many of the PCR steps ``first .. steps - 1`` the systems still need, from the
    :func:`knot_width` (``max(j1) + 2``, (1,) int64, at most ``2^steps``): (1,) int64.

    Step ``s`` is needed unless :func:`decoupled_after` holds after ``s`` steps, i.e. unless
    ``width <= 2^s + 4``; the thresholds grow with ``s``, so the steps needed are the first
    ``count`` of them (the exported sift runs them in a ``Loop`` of that many iterations).
    The count is read from a table indexed by the width: one node.
    """
    table = [sum(w > (1 << s) + 4 for s in range(first, steps)) for w in range((1 << steps) + 1)]
    return torch.tensor(table, device=width.device)[width]


def pcr_solve(sys: Tensor, j1: Tensor | None = None) -> Tensor:
    """Solve unit-diagonal tridiagonal systems by parallel cyclic reduction.

    Args:
        sys: (3, ..., K) sub-diagonal ``a``, super-diagonal ``c`` and right-hand side ``r``;
            ``a[..., 0]`` and ``c[..., K-1]`` must be 0. Strict diagonal dominance keeps it
            stable.
        j1: (..., 1) last real row of each system (rows past it are identity rows with
            right-hand side 0, as :func:`spline_system` makes them); when given, the solve
            stops as soon as :func:`decoupled_after` allows, with the same result.

    Returns:
        (1, ..., K) solution.
    """
    steps = pcr_steps(int(sys.shape[-1]))
    sys = pcr_rows(sys)
    for step in range(steps):
        if j1 is not None and j1.numel() and bool(decoupled_after(j1, step)):
            return sys[2:3]
        if step == steps - 1:
            return pcr_last(sys, 1 << step)
        sys = pcr_step(sys, 1 << step)
    raise AssertionError("unreachable: pcr_steps() >= 1")


LARGE_ROWS = 64
"""Rows (windows x channels) from which a sift lays its tensors out for many rows.

:func:`sift.prepare` then finds the end extrema by running count instead of ``TopK`` and runs
the boundary rule with the row axis last, and :func:`sift.finish` adds the two half envelopes
as two tensors; the arithmetic is the same, so the bits are (``tests/test_emd.py`` checks the
decomposition at 1 to 512 windows). onnxruntime runs these layouts faster with many rows and the
default one faster with few. The spline solver is the same at every size: a window's result
must not depend on what else is in its batch, and the Thomas algorithm, although faster from
about 32 rows on, rounds differently from PCR, which moved extrema on near-tied samples.
"""


def large_path(rows: int) -> bool:
    """True from :data:`LARGE_ROWS` rows on: the one rule by which :func:`sift.prepare` and
    :func:`sift.finish` pick their many-row layout, as the exported graph's ``If`` on the row
    count does."""
    return rows >= LARGE_ROWS


def solve(sys: Tensor, j1: Tensor | None = None) -> Tensor:
    """The spline system's solution, (3, 2, R, K) -> (1, 2, R, K), by :func:`pcr_solve` at
    every batch size (the exported graph runs the same steps, so onnxruntime and the torch
    module run the same arithmetic, and a row's result does not depend on the other rows)."""
    return pcr_solve(sys, j1)
