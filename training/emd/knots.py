"""Knots: the interior extrema and the mirrored knots of each envelope, ascending, in fixed slots.

Per envelope (axis 0: [upper, lower]) and row, knots live in ``K = N // 2 + 6`` slots. The
valid knots, in ascending order ``[left far, left near, interior extrema..., right near,
right far]``, take slots ``1 .. j1``: each knot's slot is the running count of valid knots up
to it, so one cumulative sum, one scatter of indices and one gather place them all. Slot 0
holds a placeholder position below all knots and every slot after ``j1`` a dummy position
above them, so all spacings are positive and nothing in the spline system divides by zero.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def n_slots(n_time: int) -> int:
    """Knot slots per envelope for windows of ``n_time`` samples: the placeholder, room for the
    at most ``N // 2 + 4`` knots, and at least one dummy."""
    return n_time // 2 + 6


def running_count(flags: Tensor) -> Tensor:
    """(..., L) 0/1 float flags -> (..., L) int64 running count along the last axis.

    Counted in integers: onnxruntime's ``CumSum`` takes about 15 us on 2 x 1,104 floats and
    2.5 us on as many int64 (1.32, one thread); the counts are exact either way.
    """
    return torch.cumsum(flags.long(), dim=-1)


def past_dummies(n_time: int) -> float:
    """The position one past the last dummy of :func:`slot_base` (the dummies sit at
    ``16 N + s`` in slot ``s``, above every knot, which lies within ``-N .. 2N``)."""
    return 16.0 * n_time + n_slots(n_time)


def extrema_counts(marks: Tensor) -> tuple[Tensor, Tensor]:
    """Running and total counts of the extrema.

    Args:
        marks: (2, R, N) 0/1 extremum marks.

    Returns:
        cnt: (2, R, N) extrema at samples <= t; n: (2, R, 1, 1) extrema in the row (shaped
        for :func:`end_extrema` and :func:`boundary.boundary_knots`).
    """
    cnt = running_count(marks).to(marks.dtype)
    return cnt, cnt[..., -1:].unsqueeze(-1)


def end_extrema(h: Tensor, cnt: Tensor, n: Tensor) -> tuple[Tensor, Tensor]:
    """The end samples and the first and last three extrema of each envelope, uncompacted.

    The k-th extremum (1-based) sits at the number of samples whose running count is below k;
    rank 0 gives sample 0 and rank n + 1 the last sample (after clamping).

    Args:
        h: (R, N) signals; cnt, n: (2, R, N) and (2, R, 1, 1) from :func:`extrema_counts`.

    Returns:
        p: (2, R, 2, 4) positions ``[[0, E0, E1, E2], [N-1, E[n-1], E[n-2], E[n-3]]]``;
            entries past the list hold 0 or N-1 (placeholders, never used as knots).
        v: (2, R, 2, 4) half the signal values there (see :func:`assemble`), signed: negated
            in the minima's row (:func:`boundary.boundary_knots` compares them that way).
    """
    n_time = int(h.shape[-1])
    dt, dev = h.dtype, h.device
    w = torch.tensor([0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0], dtype=dt, device=dev)
    b = torch.tensor([0.0, 1.0, 2.0, 3.0, 1.0, 0.0, -1.0, -2.0], dtype=dt, device=dev)
    rank = n * w.unsqueeze(-1) + b.unsqueeze(-1)  # (2, R, 8, 1): ranks 0..3, n+1, n, n-1, n-2
    p = (cnt.unsqueeze(-2) < rank).to(dt).sum(-1)  # (2, R, 8)
    p = torch.clamp(p, max=n_time - 1.0)
    half = torch.tensor([0.5, -0.5], dtype=dt, device=dev).reshape(2, 1, 1)
    v = torch.gather(h * half, -1, p.long())  # (2, R, 8)
    return p.reshape(2, -1, 2, 4), v.reshape(2, -1, 2, 4)


def end_base(h: Tensor) -> Tensor:
    """(R, N) signals -> (2, R, 2, 1) int64 end samples ``[0, N-1]`` of each row and envelope,
    what :func:`end_extrema_topk` puts first; it depends only on the shape (made once)."""
    ends = torch.tensor([0.0, h.shape[-1] - 1.0], dtype=h.dtype, device=h.device)
    zero = (h[:, :1] * 0.0).reshape(1, -1, 1, 1)  # (1, R, 1, 1)
    return (zero + ends.reshape(1, 1, 2, 1).expand(2, 1, 2, 1)).long()


def end_extrema_topk(
    h: Tensor, marks: Tensor, ends: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`end_extrema` by ``TopK``, with the count of the extrema (:func:`extrema_counts`).

    Args:
        h: (R, N) signals; marks: (2, R, N) 0/1 extremum marks; ends: :func:`end_base` of
            ``h`` (made here when not given).

    Returns:
        q: (2, R, 2, 4) the positions in side coordinates (:func:`boundary.side_coordinates`
            of :func:`end_extrema`'s) and v: (2, R, 2, 4) the same signed half values, wherever
            the list has an entry; past it, placeholders (never used as knots).
        n: (2, R, 1, 1) extrema in the row.

    The first three extrema are the three largest of ``marks * (N - t)``, the last three the
    three largest of ``marks * (t + 1)``: one ``TopK`` over both sides, whose indices are the
    positions and whose values give the distances from the end (``N - key`` on both sides), in
    place of :func:`end_extrema`'s comparison of every running count with every rank. Fewer
    and cheaper nodes with few rows; with many, onnxruntime's ``TopK`` is the slower (the
    exported large-batch body keeps :func:`end_extrema`). The keys of marked samples are
    distinct and positive, so ties (unmarked samples) only decide the placeholders.
    """
    n_time = int(h.shape[-1])
    dt, dev = h.dtype, h.device
    t = torch.arange(n_time, dtype=dt, device=dev)
    m4 = marks.unsqueeze(2)  # (2, R, 1, N)
    key = m4 * torch.stack([n_time - t, t + 1.0])  # (2, R, 2, N): [from the left, the right]
    top, idx = torch.topk(key, 3, dim=-1)  # (2, R, 2, 3): E0, E1, E2 / E[n-1], E[n-2], ...
    q = F.pad(n_time - top, (1, 0))  # (2, R, 2, 4): the end sample is at distance 0
    if ends is None:
        ends = end_base(h)
    half = torch.tensor([[0.5, 0.5], [-0.5, -0.5]], dtype=dt, device=dev).reshape(2, 1, 2, 1)
    v = torch.gather(h.unsqueeze(1) * half, -1, torch.cat([ends, idx], dim=-1))  # (2, R, 2, 4)
    return q, v, m4.sum(-1, keepdim=True)


def slot_base(h: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """What the knot placement starts from; it depends only on the shape, so the exported
    graph makes it once.

    Returns:
        low: (2, 2, R, 1) the placeholder knot of slot 0: position ``-16 N``, below every
            knot, value 0.
        dummies: (2, 2, R, K-1) dummy knots for slots ``1 .. K-1``: positions ``16 N + s``,
            above every knot, values 0.
        slots: (2, R, K) int64: what each slot takes when no candidate beats it: slot 0 the
            placeholder, slot ``s >= 1`` dummy ``s``.
        cands: (2, R, N + 4) int64: the index of each candidate, in knot order ``[left far,
            left near, interior 0 .. N-1, right near, right far]``, in :func:`assemble`'s table
            ``[low, mirrored 0 .. 3, interior, mirrored 0 .. 3, dummies]``: ``1, 2, 5 .. N+4,
            N+7, N+8``. Ascending in knot order, and below every dummy's index.
    """
    n_time = int(h.shape[-1])
    k = n_slots(n_time)
    dt, dev = h.dtype, h.device
    zero = h[:, :1] * 0.0  # (R, 1)
    low = torch.tensor([-16.0 * n_time, 0.0], dtype=dt, device=dev).reshape(2, 1, 1, 1)
    low = zero + low.expand(2, 2, 1, 1)  # (2, 2, R, 1)
    dummy = torch.arange(1, k, dtype=dt, device=dev) + (past_dummies(n_time) - k)
    dummies = zero + torch.stack([dummy, dummy * 0.0]).reshape(2, 1, 1, k - 1).expand(
        2, 2, 1, k - 1
    )
    t = torch.arange(n_time, dtype=dt, device=dev)
    order = torch.cat([torch.tensor([1.0, 2.0], dtype=dt, device=dev), t + 5.0,
                       torch.tensor([n_time + 7.0, n_time + 8.0], dtype=dt, device=dev)])
    cands = (zero + order.reshape(1, 1, -1).expand(2, 1, -1)).long()  # (2, R, N + 4)
    first = torch.arange(k, dtype=dt, device=dev) + (n_time + 8.0)  # dummy s at N + 8 + s
    first[0] = 0.0  # the placeholder
    slots = (zero + first.reshape(1, 1, -1).expand(2, 1, -1)).long()  # (2, R, K)
    return low, dummies, slots, cands


def assemble(
    h: Tensor,
    marks: Tensor,
    bxy: Tensor,
    bv: Tensor,
    base: tuple[Tensor, Tensor, Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """All knots of each envelope in slots ``1 .. j1``, by one cumulative count, one scatter and
    one gather.

    Args:
        h: (R, N) signals; marks: (2, R, N) 0/1 extremum marks.
        bxy: (2, 2, R, 4) mirrored knots ``[left far, left near, right near, right far]``
            (positions, half values) and bv: (2, R, 4) their 0/1 validity, from
            :func:`boundary.boundary_knots`.
        base: :func:`slot_base` of ``h``, computed here when not given.

    Returns:
        xy: (2, 2, R, K) knot positions and **half** values (``h / 2``: the two envelopes
            then sum to their mean), stacked on axis 0; the placeholder in slot 0, dummies
            after ``j1``.
        j1: (2, R, 1) last real slot (``j1`` knots).
        ks: (2, R, N) int64 slot of the last knot counted at each sample: the mirrored knots
            of the left end plus the interior extrema at or before it (for
            :func:`envelope.segment_index`, which keeps it in integers).

    Every candidate's table index is scattered to its running count of valid candidates, with
    the smaller index kept: a valid candidate's count is its slot, and the invalid candidates
    that share it come after it in knot order, so with larger indices (the table lists the
    candidates in knot order, the mirrored knots twice for that: once before the interior,
    once after). Invalid candidates before the first knot have count 0, where the
    placeholder's index 0 beats them. Positions and values are then gathered by index: half
    the scattered values of scattering positions and values themselves, and onnxruntime
    scatters about five times slower per value than it gathers.
    """
    n_time = int(h.shape[-1])
    dt, dev = h.dtype, h.device
    low, dummies, slots, cands = slot_base(h) if base is None else base
    left, right = bv.split(2, dim=-1)
    valid = torch.cat([left, marks, right], dim=-1)  # (2, R, N + 4), ascending knot order
    icount = running_count(valid)  # valid knots so far: a valid knot's slot
    src = slots.scatter_reduce(-1, icount, cands, "amin")  # (2, R, K): table index
    # Interior candidates [t, h[t] / 2] for both envelopes: (2, 1, R, N) + (2, 2, 1, N).
    t = torch.arange(n_time, dtype=dt, device=dev)
    scale = torch.tensor([0.0, 0.5], dtype=dt, device=dev).reshape(2, 1, 1, 1)
    grid = torch.stack([t, t * 0.0]).reshape(2, 1, 1, n_time).expand(2, 2, 1, n_time)
    table = torch.cat([low, bxy, h * scale + grid, bxy, dummies], dim=-1)  # (2, 2, R, N+K+8)
    xy = torch.gather(table, -1, src.expand(2, -1, -1, -1))  # (2, 2, R, K)
    return xy, icount[..., -1:].to(dt), icount[..., 2 : n_time + 2]
