"""The EMD pipeline's pieces, by name, with example inputs: for node-count budgets and tests."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from .boundary import boundary_knots, side_coordinates
from .envelope import evaluate, segment_index
from .extrema import extrema_marks, has_tie, plateau_marks, signs, strict_marks
from .knots import (
    assemble,
    end_base,
    end_extrema,
    end_extrema_topk,
    extrema_counts,
    past_dummies,
    slot_base,
)
from .sift import finish
from .spline import pcr_solve, spacings, spline_system


def piece_examples(
    rows: int = 6, n_time: int = 50, dtype: torch.dtype = torch.float64
) -> dict[str, tuple[Callable[..., object], tuple[Tensor, ...]]]:
    """Each piece of one sift with real example inputs (from a random batch)."""
    gen = torch.Generator().manual_seed(0)
    h = torch.randn(rows, n_time, generator=gen, dtype=dtype)
    d = signs(h)
    marks = extrema_marks(h)
    cnt, n = extrema_counts(marks)
    p, v = end_extrema(h, cnt, n)
    q = side_coordinates(p, n_time)
    bxy, bv = boundary_knots(h, q, v, n)
    xy, j1, ks = assemble(h, marks, bxy, bv)
    hk, sl = spacings(xy, past_dummies(n_time))
    system = spline_system(xy, j1, hk, sl)
    m = pcr_solve(system)
    seg = segment_index(ks, j1)
    n_ext = n.sum(dim=(0, 3))
    active = torch.ones(rows, 1, dtype=torch.bool)
    return {
        "head": (lambda h: (d := signs(h), has_tie(d)), (h,)),
        "strict": (strict_marks, (d,)),
        "plateau": (plateau_marks, (d,)),
        "end_topk": (end_extrema_topk, (h, marks, end_base(h))),
        "counts": (extrema_counts, (marks,)),
        "end_extrema": (end_extrema, (h, cnt, n)),
        "sides": (lambda p: side_coordinates(p, n_time), (p,)),
        "boundary": (boundary_knots, (h, q, v, n)),
        "assemble": (
            lambda h, m, xy, v, *base: assemble(h, m, xy, v, base),
            (h, marks, bxy, bv, *slot_base(h)),
        ),
        "spacings": (lambda xy: spacings(xy, past_dummies(n_time)), (xy,)),
        "system": (spline_system, (xy, j1, hk, sl)),
        "solve": (pcr_solve, (system,)),
        "segment": (segment_index, (ks, j1)),
        "evaluate": (evaluate, (h, xy, m, seg, hk, sl)),
        "finish": (finish, (h, active, xy, m, j1, ks, n_ext, hk, sl)),
    }
