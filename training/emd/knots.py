"""Knot slots: interior extrema and mirrored knots, ascending, in fixed-size arrays.

Per envelope (axis 0: [upper, lower]) and row, knots live in ``K = N // 2 + 5`` slots:

* slots 0, 1: left mirrored knots, right-aligned (a single valid one sits in slot 1);
* slots 2 .. n+1: the n interior extrema, compacted by a cumulative count and one scatter;
* slots n+2, n+3: right mirrored knots, left-aligned.

The real knots are slots ``j0 .. j1``. Every other slot holds a dummy position below or above
all knots, so all spacings are positive and nothing in the spline system divides by zero.
"""

from __future__ import annotations

import torch
from torch import Tensor


def n_slots(n_time: int) -> int:
    """Knot slots per envelope for windows of ``n_time`` samples."""
    return n_time // 2 + 5


def _dummy_positions(n_time: int, dt: torch.dtype, dev: torch.device) -> Tensor:
    """(K + 1,) initial slot positions: two far left, the rest far right (last = dump)."""
    k = n_slots(n_time)
    pos = torch.arange(k + 1, dtype=dt, device=dev) + 16.0 * n_time
    pos[:2] = torch.tensor([-8.0 * n_time, -8.0 * n_time + 1.0], dtype=dt)
    return pos


def compact_extrema(h: Tensor, marks: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Interior extrema into slots 2 .. n+1.

    Args:
        h: (R, N) signals; marks: (2, R, N) 0/1 extremum marks.

    Returns:
        cnt: (2, R, N) running count of extrema (knots among samples <= t).
        n: (2, R, 1) number of extrema.
        x, y: (2, R, K + 1) slot positions and values; slot K is a dump slot. Dummy slots
            carry finite meaningless values.
    """
    n_time = int(h.shape[-1])
    k = n_slots(n_time)
    dt, dev = h.dtype, h.device
    cnt = torch.cumsum(marks, dim=-1)  # (2, R, N)
    n = cnt[..., -1:]  # (2, R, 1)
    slot = torch.where(marks > 0, cnt + 1.0, float(k)).long()  # (2, R, N)
    t = torch.arange(n_time, dtype=dt, device=dev)  # (N,)
    init = n * 0.0 + _dummy_positions(n_time, dt, dev)  # (2, R, K + 1)
    x = init.scatter(-1, slot, marks * 0.0 + t)  # (2, R, K + 1)
    # Values by gather (cheaper than a second scatter); dummy slots read a clamped sample.
    src = torch.clamp(x, 0.0, n_time - 1.0).long()  # (2, R, K + 1)
    y = torch.gather(h.unsqueeze(0).expand(2, -1, -1), -1, src)  # (2, R, K + 1)
    return cnt, n, x, y


def place_boundary(
    x: Tensor, y: Tensor, n: Tensor, bx: Tensor, by: Tensor, bv: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Write the mirrored knots next to the interior ones.

    Args:
        x, y: (2, R, K + 1) from :func:`compact_extrema`; n: (2, R, 1).
        bx, by, bv: (2, R, 4) mirrored knots ``[left far, left near, right near, right far]``
            (positions, values, 0/1 validity).

    Returns:
        x, y: (2, R, K) all knots; j0, j1: (2, R, 1) first and last real slot.
        kx, kv: (2, R, 4) the mirrored knots as placed (positions, 0/1 validity), for
            :func:`envelope.segment_index`.
    """
    k = int(x.shape[-1]) - 1
    idx = torch.tensor([0, 0, 3, 3], device=x.device)
    # Right-align the left pair and left-align the right pair: where the inner knot of a side
    # is missing, its outer knot takes the inner slot.
    inner = torch.index_select(bv, -1, torch.tensor([1, 1, 2, 2], device=x.device)) > 0
    kx = torch.where(inner, bx, torch.index_select(bx, -1, idx))  # (2, R, 4)
    ky = torch.where(inner, by, torch.index_select(by, -1, idx))  # (2, R, 4)
    keep = torch.tensor([0.0, 1.0, 1.0, 0.0], dtype=x.dtype, device=x.device)
    kv = torch.where(inner, bv, torch.index_select(bv, -1, idx) * keep)  # (2, R, 4)
    w = torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=x.dtype, device=x.device)
    b = torch.tensor([0.0, 1.0, 2.0, 3.0], dtype=x.dtype, device=x.device)
    slot = torch.where(kv > 0, n * w + b, float(k)).long()  # (2, R, 4): dump when invalid
    x = x.scatter(-1, slot, kx)[..., :k]  # (2, R, K)
    y = y.scatter(-1, slot, ky)[..., :k]  # (2, R, K)
    # j0 = 2 - (valid left knots), j1 = n + 1 + (valid right knots), as one small product.
    w = torch.tensor(
        [[-1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, 1.0]], dtype=x.dtype, device=x.device
    )
    j0, j1 = (kv @ w + torch.tensor([2.0, 1.0], dtype=x.dtype, device=x.device)).split(1, -1)
    j1 = j1 + n  # (2, R, 1)
    return x, y, j0, j1, kx, kv
