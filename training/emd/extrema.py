"""Extrema of a batch of signals, exactly as PyEMD's ``'simple'`` detection finds them.

PyEMD marks sample ``i`` a maximum when the slope changes from rising to falling there, and
handles flat runs (ties, common in integer pen data) with a plateau rule: a flat run that is
entered rising and left falling gives one maximum at the rounded middle of the run. Three
quirks of its port of the MATLAB code are reproduced (EMD_SPEC §1.4):

1. a flat run starting at difference index 1 is dropped;
2. a flat run starting at index 0 takes the *last* difference as its entry slope (wrap-around);
3. a flat run reaching the end is dropped.

Fixed-shape formulation: both cases are one rule over pairs of consecutive *non-zero*
differences ``(j, e)``: if their signs differ there is an extremum at sample
``round((j + 1 + e) / 2)`` (``e == j + 1`` is the strict case). The non-zero differences are
compacted with a cumulative sum and a scatter-add, so "the next non-zero difference" is one
gather. A virtual pair at ``j = -1`` carrying the last difference implements quirk 2.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

_BIG = 1e9


def signs(h: Tensor) -> Tensor:
    """(R, N) signals -> (R, N) signs of the first differences ``h[t+1] - h[t]``, and +1 in the
    last column (the difference to +inf past the end: never zero, never read as a slope).

    N columns rather than N-1, so that the shifted copy :func:`strict_marks` needs is one
    ``Pad``, and the differences themselves are one ``Pad`` and one ``Sub`` (finite input).
    """
    return torch.sign(F.pad(h, (-1, 1), value=math.inf) - h)


def has_tie(sg: Tensor) -> Tensor:
    """True (a 0-d bool tensor) when any difference is exactly zero: a flat run somewhere.

    ``sg``: :func:`signs` of the signals (R, N); both extremum rules start from it.

    Without ties the plateau rule reduces to the strict rule, so the exported sift keeps the
    cheap :func:`strict_marks` whenever this is false and runs the plateau rule in a ``Loop`` of
    one iteration only when it is true. Quantised
    data have ties in the first sift; once a mean envelope has been subtracted they are rare.
    """
    return sg.abs().amin() == 0.0  # exact; a min, not a product: onnxruntime 1.19 has no
    # float64 ReduceProd


def strict_marks(sg: Tensor) -> Tensor:
    """Extremum marks from :func:`signs` (R, N), none zero, N >= 2: (R, N) -> (2, R, N) 0/1
    [max, min].

    A sample is a maximum where the slope turns from rising to falling: the sign of the
    differences drops by 2 there (rises by 2 at a minimum). End samples are never extrema.
    """
    n = int(sg.shape[-1])
    turn = F.pad(sg, (1, -1)) - sg  # (R, N): +2 at maxima, -2 at minima
    # Half the sign change, signed per envelope, and 0 at the end samples (where ``turn`` holds
    # no real change): (2, 1, N).
    half = torch.tensor([0.5, -0.5], dtype=sg.dtype, device=sg.device).reshape(2, 1, 1)
    half = F.pad(half.expand(2, 1, max(n - 2, 0)), (1, 1))
    return torch.relu(turn * half)  # (2, R, N)


def plateau_signed(sg: Tensor) -> Tensor:
    """Signed extremum marks from the differences' signs (R, N-1), with the plateau rule.

    ``sg`` holds the N-1 real differences' signs (:func:`signs` without its last column).

    Returns:
        (R, N) tensor of sg's dtype: +1 at maxima, -1 at minima, 0 elsewhere. End samples are
        never extrema, except through quirk 2, as in PyEMD.
    """
    n = int(sg.shape[-1]) + 1
    dt, dev = sg.dtype, sg.device
    # Column c holds the pair starting at difference j = c - 1; column 0 is the virtual pair.
    sgp = torch.cat([sg[:, -1:], sg], dim=-1)  # (R, N)
    # rank[c]: number of non-zero differences before column c's own (its 1-based rank).
    ri = torch.cumsum(F.pad(sg.abs(), (1, 0)).long(), dim=-1)  # (R, N): integer CumSum is
    rank = ri.to(dt)  # several times faster in onnxruntime (knots.running_count)
    col = torch.arange(n, dtype=dt, device=dev)  # (N,) = j + 1
    # code[r] = sign * (j + 1) of the r-th non-zero difference: zero differences add 0 and the
    # virtual column adds sign * 0, so a scatter-add compacts without any select.
    zeros = rank * 0.0  # (R, N)
    code = F.pad(zeros, (0, 1)).scatter_add(-1, ri, sgp * col)  # (R, N+1)
    nxt = torch.gather(code, -1, ri + 1)  # (R, N): next non-zero difference, 0 if none (quirk 3)
    a = nxt.abs()  # (R, N) = e + 1
    # Column 0 counts only if d[0] == 0 (e > 0); column 1 (j = 0) only without a gap (quirk 1).
    lo = torch.zeros(n, dtype=dt, device=dev)
    lo[0] = 1.0
    hi = torch.full((n,), _BIG, dtype=dt, device=dev)
    hi[1] = 2.0
    ok = (sgp * torch.sign(nxt) < 0) & (a > lo) & (a <= hi)  # (R, N)
    val = torch.where(ok, sgp, zeros)  # (R, N): +1 rising into a maximum, -1 into a minimum
    mid = torch.round((a + (col - 1.0)) * 0.5).long()  # (R, N) in [0, N-1], half to even
    # Midpoints of different pairs are distinct and non-extrema add 0: no dump slot needed.
    return zeros.scatter_add(-1, mid, val)  # (R, N)


def plateau_marks(sg: Tensor) -> Tensor:
    """(R, N) :func:`signs` -> (2, R, N) 0/1 marks [maxima, minima], plateau rule included."""
    sign = torch.tensor([1.0, -1.0], dtype=sg.dtype, device=sg.device).reshape(2, 1, 1)
    return (plateau_signed(sg[:, :-1]) * sign > 0).to(sg.dtype)


def find_extrema(h: Tensor) -> Tensor:
    """(R, N) signals, N >= 3 -> (R, N) signed marks: +1 at maxima, -1 at minima."""
    return plateau_signed(signs(h)[:, :-1])


def extrema_marks(h: Tensor) -> Tensor:
    """(R, N) signals -> (2, R, N) 0/1 marks, envelope axis first: [maxima, minima].

    Eager form of the exported choice: the plateau rule only when some difference is zero.
    """
    sg = signs(h)
    return plateau_marks(sg) if sg.numel() and bool(has_tie(sg)) else strict_marks(sg)
