"""The EMD graph's pieces and node counts, for node-count budgets (``bench/emd.py --pieces``,
``tests/test_emd_onnx.py``): each piece of one sift by name with example inputs
(:func:`piece_examples`), and the node counts of the exported graph's ``Loop`` bodies and
``If`` branches (:func:`subgraphs`, :func:`sift_path_nodes`, :func:`count_nodes`).

Imported by the benchmark (``bench/`` is its script folder) and loaded by file by the tests.
"""

from __future__ import annotations

from collections.abc import Callable

import onnx
import torch
from torch import Tensor

from tactile.export.emd_graph import PCR_ALWAYS
from tactile.training.emd.boundary import boundary_knots, side_coordinates
from tactile.training.emd.envelope import evaluate, segment_index
from tactile.training.emd.extrema import extrema_marks, has_tie, plateau_marks, signs, strict_marks
from tactile.training.emd.knots import (
    assemble,
    end_base,
    end_extrema,
    end_extrema_topk,
    extrema_counts,
    n_slots,
    past_dummies,
    slot_base,
)
from tactile.training.emd.sift import finish
from tactile.training.emd.spline import pcr_solve, pcr_steps, spacings, spline_system


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


def subgraphs(graph: onnx.GraphProto) -> dict[str, onnx.GraphProto]:
    """Every subgraph (Loop bodies such as ``imf`` and ``sift``, If branches) by name, nested
    ones included."""
    out: dict[str, onnx.GraphProto] = {}
    for node in graph.node:
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                out[attr.g.name] = attr.g
                out.update(subgraphs(attr.g))
    return out


def subgraph_nodes(graph: onnx.GraphProto) -> dict[str, int]:
    """Node count of every subgraph by name (:func:`subgraphs`)."""
    return {name: len(g.node) for name, g in subgraphs(graph).items()}


def sift_path_nodes(model: onnx.ModelProto, n_time: int, large: bool = False) -> tuple[int, int]:
    """Nodes one sift runs on input without ties: (fewest, most); ``large``: in the body for
    :data:`spline.LARGE_ROWS` rows or more.

    Fewest: the loop body alone (the :data:`PCR_ALWAYS` steps, the solution taken after them);
    most: with every remaining PCR step, an iteration of the PCR loop each.
    """
    graphs = subgraph_nodes(model.graph)
    suffix = "_large" if large else ""
    steps = pcr_steps(n_slots(n_time))
    always = min(PCR_ALWAYS, steps - 1)
    base = graphs["sift" + suffix]
    return base, base + (steps - always) * graphs["pcr" + suffix]


def count_nodes(graph: onnx.GraphProto) -> int:
    """Nodes in ``graph`` and all its subgraphs (each Loop body counted once)."""
    total = 0
    for node in graph.node:
        total += 1
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                total += count_nodes(attr.g)
    return total
