"""Envelope evaluation: the cubic spline through the knots, at every sample.

All knots sit at integer positions, so the segment holding sample ``t`` is a count (knots at
or before ``t``) rather than a search. Each segment's cubic is written in the local power basis
scipy's ``PPoly`` uses, ``y_k + B (c1 + B (c2 + B c3))`` with ``B = t - x_k``, and five gathers
with the same index fetch the five numbers per sample (cheaper in onnxruntime than one gather
of the five stacked, whose index must be broadcast and whose result must be split).
Not-a-knot splines evaluate their outer segments with the neighbouring segment's cubic (the
same polynomial), so ``M`` at the end knots is never needed. A sample on a knot that starts
its segment gets the knot's value exactly (``B = 0``), as scipy returns it; on the two outer
knots of a not-a-knot spline, up to rounding.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .spline import pick, spacings


def segment_index(ks: Tensor, j1: Tensor) -> Tensor:
    """Segment of every sample.

    Args:
        ks: (2, R, N) int64, the left end's valid mirrored knots plus the interior extrema at
            or before each sample (:func:`knots.assemble`: knots sit in slots ``1 .. j1``).
        j1: (2, R, 1) last real knot slot.

    Returns:
        (1, 2, R, N) int64 slot ``k`` of the segment ``[x_k, x_{k+1}]`` evaluated at ``t``: the last
        knot at or before ``t``, clamped to ``[2, j1-2]`` for not-a-knot splines and to
        ``[1, j1-1]`` for 3-knot natural ones.

    ``ks`` counts the left knots at every sample and the right knots at none, though either
    kind can sit inside the window (mirrored about an extremum, or on the end sample). After
    clamping this changes nothing: a left knot is missed only before the left knots end, where
    the count is at most 2 and the true value at most 1, and both clamp to the low end
    unless the spline is the natural 3-knot one with two left knots; a right knot is missed
    only after the interior ends, where both clamp to the high end unless the spline is the
    natural one with two right knots. Those two cases cannot occur: an envelope with one
    interior extremum always has a valid near knot at each end (its first source, the end
    sample or E0, always exists), so its three knots are one left, E0 and one right.
    """
    # Not-a-knot (j1 >= 4) clamps to [2, j1-2], natural 3-knot (j1 = 3) to [1, 2]; rows
    # without an envelope (j1 < 3) stay inside [1, 2]. In integers, like ks: no cast of the
    # (2, R, N) counts.
    two = torch.full((1, 1, 1, 1), 2, dtype=torch.int64, device=j1.device)
    j2 = j1.long() - two  # (1, 2, R, 1): the leading axis comes with the broadcast, not a node
    lo = torch.clamp(j2, 1, 2)
    hi = torch.clamp(j2, min=2)
    # Slot of the last knot at or before t: the knots <= t.
    return torch.minimum(torch.maximum(ks, lo), hi)


def evaluate(
    h: Tensor, xy: Tensor, m: Tensor, seg: Tensor, hk: Tensor | None = None,
    sl: Tensor | None = None,
) -> Tensor:
    """Evaluate the splines at t = 0..N-1.

    Args:
        h: (R, N) signals (only the length is used).
        xy: (2, 2, R, K) knot positions and values; m: (1, 2, R, K) second derivatives over 6.
        seg: (1, 2, R, N) int64 segment slot per sample (:func:`segment_index`).
        hk, sl: (1, 2, R, K) :func:`spline.spacings` of ``xy``, computed here when not given.

    Returns:
        (1, 2, R, N) envelopes.
    """
    n_time = int(h.shape[-1])
    if hk is None or sl is None:
        hk, sl = spacings(xy)
    dm = F.pad(m, (-1, 1)) - m  # (1, 2, R, K): m_k+1 - m_k (slot K-1 a placeholder)
    # scipy's PPoly form of the cubic on [x_k, x_k+1]: y_k + B (c1 + B (c2 + B c3)), with
    # c2 = M_k / 2 = 3 m_k, c3 = (M_k+1 - M_k) / (6 h) and c1 = slope - h (2 M_k + M_k+1) / 6.
    c2 = 3.0 * m
    c1 = sl - hk * (c2 + dm)
    x0, y0 = pick(xy, 0, 1)  # (1, 2, R, K) each; segments start below slot K-1
    gx, gy, g1, g2, g3 = (torch.gather(c, -1, seg) for c in (x0, y0, c1, c2, dm / hk))
    t = torch.arange(n_time, dtype=xy.dtype, device=xy.device)  # (N,)
    b = t - gx
    return gy + b * (g1 + b * (g2 + b * g3))  # (1, 2, R, N)
