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
    hk, dy = (nxt - xy).split(1)  # spacings (all > 0), rises
    return hk, dy / hk


def spline_system(
    xy: Tensor, j1: Tensor, hk: Tensor | None = None, sl: Tensor | None = None
) -> Tensor:
    """Tridiagonal rows for the knots' second derivatives over 6, each divided by its diagonal.

    Args:
        xy: (2, ..., K) knot positions (strictly increasing over all K slots) and values; the
            real knots are slots ``1 .. j1``.
        j1: (..., 1) last real knot slot (``j1 >= 3`` for real rows).
        hk, sl: (1, ..., K) :func:`spacings` of ``xy``, computed here when not given.

    Returns:
        (3, ..., K): sub-diagonal, super-diagonal and right-hand side of the unit-diagonal rows
        whose solution is ``M / 6`` (the right-hand side is the slope change, without the 6).
    """
    k = int(xy.shape[-1])
    dt, dev = xy.dtype, xy.device
    j = torch.arange(k, dtype=dt, device=dev)  # (K,)
    row2 = (j == 2.0).to(dt)  # (K,) row 2: M[1] eliminated (or natural)
    if hk is None or sl is None:
        hk, sl = spacings(xy)  # (1, ..., K) each
    hm = F.pad(hk, (1, -1), value=1.0)  # (1, ..., K): h[j-1]
    hp = hk  # (1, ..., K): h[j]; the placeholder in row K-1 is positive
    rhs = sl - F.pad(sl, (1, -1))  # (1, ..., K); rows 0, 1 and K-1 are masked
    # Distance from the last knot, with rows 0 and 1 placed past every slot: negative there,
    # so one clamp masks both ends (and they are never taken for the right not-a-knot row).
    dr = j1 - torch.where(j < 1.5, float(k), j)  # (..., K)
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


THOMAS_ROWS = 64
"""Rows (windows x channels) from which :func:`solve` uses :func:`thomas_solve`.

The two solvers trade differently in onnxruntime: PCR is at most 67 nodes (five steps of 13 or
14 and the diagonal's row) on full-width tensors (fewer once the systems decouple), the Thomas
algorithm about ``8 K`` nodes on one column each. With few rows every node costs about the same
fixed microsecond, so fewer nodes win; with many rows the work per element decides, and the
Thomas algorithm does ``O(K)`` of it against PCR's ``O(K log K)``. ``bench/emd.py --solvers``
measures the crossover for 50-sample windows (32-48 rows with fresh sessions, where the two
exported bodies also differ in how they find the end extrema; 64 costs a few percent in
between).
"""


def large_path(rows: int) -> bool:
    """True from :data:`THOMAS_ROWS` rows on: the one rule by which :func:`solve`,
    :func:`sift.prepare` and :func:`sift.finish` pick their many-row path, as the exported
    graph's ``If`` on the row count does."""
    return rows >= THOMAS_ROWS


SPLINE_EDGES = (2, 2)
"""Identity rows every spline system has at its two ends (:func:`spline_system` with
:mod:`knots`' layout): the placeholder's and the first knot's rows; the always-dummy last slot's
and the one before, which is a dummy's or the last knot's (at most ``K - 2`` knots)."""


def thomas_solve(sys: Tensor, lead: int = 0, trail: int = 0) -> Tensor:
    """Solve unit-diagonal tridiagonal systems by the Thomas algorithm (no pivoting).

    Args:
        sys: (3, ..., K) sub-diagonal ``a``, super-diagonal ``c`` and right-hand side ``r``, as
            for :func:`pcr_solve` (``a[..., 0] = c[..., K-1] = 0``, strictly diagonally
            dominant: ``|a| + |c| < 1``). Then the elimination is stable: by induction every
            ``|c'| < 1``, so every pivot exceeds ``1 - |a| > |c| >= 0``.
        lead, trail: the first ``lead`` and the last ``trail`` rows are identity rows
            (``a = c = r = 0``) in every system, as :data:`SPLINE_EDGES` are for the spline
            systems: the sweeps skip them (their ``r``, 0, is the solution), with the same
            result as sweeping them, bit for bit.

    Returns:
        (1, ..., K) solution. Identity rows (``a = c = r = 0``) get exactly 0, as from PCR; real
        rows agree with :func:`pcr_solve` to rounding (both are exact elimination orders).

    Forward sweep: ``c'[j] = c[j] / p[j]`` and ``r'[j] = (r[j] - a[j] r'[j-1]) / p[j]`` with
    pivot ``p[j] = 1 - a[j] c'[j-1]``; back substitution: ``x[j] = r'[j] - c'[j] x[j+1]``. The
    columns are split once, so each step is a few elementwise nodes on (1, ..., 1) tensors.
    """
    a, c, r = sys.split(1)  # (1, ..., K) each
    cols_a, cols_c, cols_r = (t.split(1, dim=-1) for t in (a, c, r))  # K x (1, ..., 1)
    end = len(cols_a) - trail
    # The first swept row has pivot 1: a[0] = 0, or the row before is an identity row.
    cp, rp = [cols_c[lead]], [cols_r[lead]]
    for j in range(lead + 1, end):
        pivot = 1.0 - cols_a[j] * cp[-1]
        cp.append(cols_c[j] / pivot)
        rp.append((cols_r[j] - cols_a[j] * rp[-1]) / pivot)
    x = [rp[-1]]  # the row after the last swept one is an identity row (or there is none)
    for j in range(len(rp) - 2, -1, -1):
        x.append(rp[j] - cp[j] * x[-1])
    return torch.cat([*cols_r[:lead], *x[::-1], *cols_r[end:]], dim=-1)


def solve(sys: Tensor, j1: Tensor | None = None) -> Tensor:
    """The spline system's solution, (3, 2, R, K) -> (1, 2, R, K): :func:`thomas_solve` from
    :data:`THOMAS_ROWS` rows on, :func:`pcr_solve` below (the exported graph makes the same
    choice, so onnxruntime and the torch module run the same arithmetic)."""
    if large_path(int(sys.shape[2])):
        return thomas_solve(sys, *SPLINE_EDGES)
    return pcr_solve(sys, j1)
