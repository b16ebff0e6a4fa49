"""Boundary knots: PyEMD's port of Rilling's ``boundary_conditions.m`` (EMD_SPEC §1.5).

Each envelope gets up to two mirrored knots beyond each end. The right end is the left end
seen backwards, and the minima's rule is the maxima's rule with the signal negated, so the
code works in *side coordinates* (distance from the end in question) and in *roles*: ``F`` is
the envelope whose first extremum comes first from that end, ``G`` the other one. All
quantities are computed for both envelopes and both ends at once, shape (2, R, 2, .).

With ``F0 < G0`` the first positions, ``vG0`` the value at ``G0`` and ``sigma = +1`` when F
holds the maxima (``-1`` for minima), the spec's eight cases collapse to three:

* case 1 (A1/B1/C1/D1), ``sigma * (S[end] - vG0) > 0``: mirror about ``F0``; F sources
  ``F[1:3]``, G sources ``G[0:2]``;
* fallback, case 1 whose outermost mirrored knot does not reach past the end: mirror about
  the end; F sources ``F[0:2]``, G sources ``G[0:2]``;
* case 2 (A2/B2/C2/D2): mirror about the end; F sources ``F[0:2]``, G sources the end sample
  and ``G0``.

So each envelope takes two consecutive sources from ``[end sample, E0, E1, E2]``, shifted by
0, 1 or 2. A knot landing on the envelope's first interior extremum is the duplicate PyEMD
deletes; it is marked invalid (the only place a duplicate can occur).
"""

from __future__ import annotations

import torch
from torch import Tensor


def side_coordinates(p: Tensor, n_time: int, rows_last: bool = False) -> Tensor:
    """Sample positions -> distances from the end each list is seen from.

    ``p``: (2, R, 2, 4) positions of ``[end sample, E0, E1, E2]`` from each end
    (:func:`knots.end_extrema`), or (2, 2, 4, R) with ``rows_last``; the left end's are
    unchanged, the right end's become ``N - 1 - p``.
    """
    dt, dev = p.dtype, p.device
    rows = (1,) if rows_last else ()
    side_sign = torch.tensor([1.0, -1.0], dtype=dt, device=dev).reshape(2, 1, *rows)
    side_off = torch.tensor([0.0, n_time - 1.0], dtype=dt, device=dev).reshape(2, 1, *rows)
    return p * side_sign + side_off


def boundary_knots(
    h: Tensor, q: Tensor, v: Tensor, n: Tensor, rows_last: bool = False
) -> tuple[Tensor, Tensor]:
    """The mirrored knots of both envelopes at both ends.

    Args:
        h: (R, N) signals (only the length is used).
        q: (2, R, 2, 4) distances from each end (:func:`side_coordinates`) of
            ``[end sample, E0, E1, E2]`` seen from that end; v: (2, R, 2, 4) the *signed* half
            values there, ``sigma * S / 2`` with ``sigma = +1`` for the maxima' row and ``-1``
            for the minima's (:func:`knots.end_extrema`); n: (2, R, 1, 1) extrema counts.

    Returns:
        xy: (2, 2, R, 4) knot positions and half values (signs undone), ordered
            ``[left far, left near, right near, right far]`` (ascending when valid).
        valid: (2, R, 4) 0/1 floats. Rows with fewer than 3 extrema get meaningless knots.

    With ``rows_last`` every tensor has the row axis last instead: ``q``, ``v`` (2, 2, 4, R),
    ``n`` (2, 1, 1, R); returns ``xy`` (2, 2, 4, R) and ``valid`` (2, 4, R). The same
    elementwise operations and gathers, so the same bits; onnxruntime broadcasts over a long
    innermost axis far faster than over the short side and source axes (the exported graph's
    large-batch body uses it).
    """
    n_time = int(h.shape[-1])
    dt, dev = h.dtype, h.device
    ax = -2 if rows_last else -1  # the sources' axis
    # Left side takes sources [far, near], right side [near, far]: ascending positions at once.
    kvec = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=dt, device=dev)
    kvec = kvec.reshape(2, 2, 1) if rows_last else kvec
    # Single entries and the envelope swap by index (onnxruntime's Gather costs less than the
    # Slice that narrow and flip become).
    def pick(t: Tensor, dim: int, *i: int) -> Tensor:
        return t.index_select(dim, torch.tensor(i, device=dev))

    first = pick(q, ax, 1)  # (2, R, side, 1)
    other = pick(first, 0, 1, 0)  # the other envelope's first extremum
    is_f = first < other  # (2, R, side, 1): this envelope plays F
    f0 = torch.minimum(first, other)
    # Case 1 seen from either envelope: sigma_F * (S[end] - vG0) > 0, i.e. G's own
    # sigma_G * (vG0 - S[end]) > 0 (sigma_G = -sigma_F), read from G's row when this one is F.
    own = pick(v, ax, 1) - pick(v, ax, 0)  # (2, R, side, 1): signed values
    case1 = torch.where(is_f, pick(own, 0, 1, 0), own) > 0
    # Fallback: the outermost case-1 knot of F (source F[min(2, nF-1)]) or of G (source
    # G[min(1, nG-1)]) would not reach past the end (list index + 1: the end sample is first).
    own_last = torch.gather(q, ax, torch.minimum(is_f.to(dt) + 2.0, n).long())
    two_f0 = 2.0 * f0
    reach = own_last >= two_f0  # (2, R, side, 1): not the fallback for this envelope
    case1 = case1.to(dt)
    # Both envelopes' outermost knots reach past the end: the smaller 0/1 over the two.
    mirror_f0 = case1 * reach.to(dt).amin(0, keepdim=True)  # (2, R, side, 1)
    shift = torch.where(is_f, mirror_f0 + 1.0, case1)  # (2, R, side, 1) in 0..2
    src = shift + kvec  # (2, R, side, k): index in [end sample, E0, E1, E2]
    idx = src.long()
    kx = two_f0 * mirror_f0 - torch.gather(q, ax, idx)  # mirrored, side coordinates
    val = torch.gather(v, ax, idx)
    # A source exists when the list is long enough; a knot on E0 duplicates it.
    valid = (src <= n) & (kx < first)
    # [kx, val] (4, R, side, k): positions back from side coordinates, values unsigned.
    scale = torch.tensor([[1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, -1.0]], dtype=dt,
                         device=dev)
    offset = torch.tensor([[0.0, n_time - 1.0]] * 2 + [[0.0, 0.0]] * 2, dtype=dt, device=dev)
    shape = (4, 2, 1, 1) if rows_last else (4, 1, 2, 1)
    xy = torch.cat([kx, val]) * scale.reshape(shape) + offset.reshape(shape)
    if rows_last:
        return xy.reshape(2, 2, 4, -1), valid.to(dt).reshape(2, 4, -1)
    return xy.reshape(2, 2, -1, 4), valid.to(dt).reshape(2, -1, 4)
