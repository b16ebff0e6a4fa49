"""Where each sparse coder sits in an exported graph, and a copy of the graph that shows it.

A model whose preprocessing holds :class:`~tactile.training.sparse.SparseCoder` modules (the
``sf_rnn`` and ``sparse_linear`` models: one coder per modality) has each coder traced into the
graph's ``post`` part as a sub-graph: the nodes whose scope is the coder's module (the
exporter names a node ``.../<scope>/<op>``, the scope being the coder's qualified name in the
model, or its tail). Its one input from outside the scope is the images ``(rows, features)``
(rows = windows x steps) and its one output used outside is the codes ``(rows, atoms)``
(:func:`find_coders`). To observe them, the file's own graph is copied with those values (and
each OMP step's pick) added as outputs, the nodes unchanged (:func:`tapped`), and run by
onnxruntime (:func:`tap_session`): the code parity (:mod:`tactile.export.codes`) and the
excuses for near-tie flips (:mod:`tactile.export.ties`) both read the coders this way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto, helper
from torch import nn

from tactile.contract import CUSTOM_DOMAIN
from tactile.errors import ModelContractError
from tactile.export.session import session
from tactile.training.sparse import SparseCoder


class CoderNotFound(ModelContractError):
    """A coder of the model could not be located in the graph."""


@dataclass(frozen=True)
class CoderTap:
    """Where one coder sits in the graph: its module path in the model, the value it reads
    (images, rows x features) and the value it writes (codes, rows x atoms), its node count."""

    path: str
    coder: SparseCoder
    x: str
    codes: str
    nodes: tuple[onnx.NodeProto, ...]


def coders(model: nn.Module) -> list[tuple[str, SparseCoder]]:
    """The model's coders with their qualified names, in module order."""
    return [(p, m) for p, m in model.named_modules() if isinstance(m, SparseCoder)]


def _scope(node: onnx.NodeProto) -> str:
    """The last scope segment of a traced node's name (``/pre/coders.0/MatMul`` ->
    ``coders.0``; composed graphs prefix ``post/``)."""
    parts = node.name.split("/")
    return parts[-2] if len(parts) >= 3 else ""


def portable(graph: onnx.ModelProto, found: list[tuple[str, SparseCoder]]) -> onnx.ModelProto:
    """``graph`` with each ``ai.tactile::SparseCode`` node (a coder as one node, its
    ``variant`` the index into ``found``) replaced by the body the file's fallback function
    runs for it (the coder's own traced graph), its nodes named ``/<path>/<op>_<i>`` so that
    its scope is the coder's; ``graph`` itself when it has no such node."""
    if not any(n.domain == CUSTOM_DOMAIN and n.op_type == "SparseCode" for n in graph.graph.node):
        return graph
    from tactile.export.compose import renamed
    from tactile.export.custom_ops import variant_body

    (fn,) = [f for f in graph.functions if f.domain == CUSTOM_DOMAIN and f.name == "SparseCode"]
    out = onnx.ModelProto()
    out.CopyFrom(graph)
    nodes = []
    for node in graph.graph.node:
        if node.domain != CUSTOM_DOMAIN or node.op_type != "SparseCode":
            nodes.append(node)
            continue
        variant = next(a.i for a in node.attribute if a.name == "variant")
        path = found[variant][0]
        body, outs = variant_body(fn, variant)
        wire = dict(zip(fn.input, node.input, strict=True))
        wire.update(zip(outs, node.output, strict=True))
        g = renamed(onnx.helper.make_model(onnx.helper.make_graph(body, "coder", [], [])),
                    f"{path}/", wire)
        for i, n in enumerate(g.node):
            n.name = f"/{path}/{n.op_type}_{i}"
        nodes += list(g.node)
    del out.graph.node[:]
    out.graph.node.extend(nodes)
    return out


def find_coders(model: nn.Module, graph: onnx.ModelProto) -> list[CoderTap]:
    """Locate every coder of ``model`` in ``graph``: :class:`CoderNotFound` unless each has
    exactly one outside input and one output used outside its scope. A coder exported as one
    ``SparseCode`` node is located in its portable form (:func:`portable`)."""
    g = portable(graph, coders(model)).graph
    consts = {i.name for i in g.initializer}
    consts |= {o for n in g.node if n.op_type == "Constant" for o in n.output}
    found = coders(model)
    taps = []
    for path, coder in found:
        comps = path.split(".")
        tails = {".".join(comps[i:]) for i in range(len(comps) - 1)} or {path}
        nodes = [n for n in g.node if _scope(n) in tails]
        if not nodes:
            raise CoderNotFound(f"coder {path!r}: no node of its scope in the graph")
        inside = {id(n) for n in nodes}
        made = {o for n in nodes for o in n.output}
        ins = {v for n in nodes for v in n.input if v and v not in made and v not in consts}
        used = {v for n in g.node if id(n) not in inside for v in n.input}
        used |= {o.name for o in g.output}
        outs = [v for v in dict.fromkeys(o for n in nodes for o in n.output) if v in used]
        if len(ins) != 1 or len(outs) != 1:
            raise CoderNotFound(f"coder {path!r}: its sub-graph reads {sorted(ins)} and "
                                f"writes {outs}; expected one input and one output")
        taps.append(CoderTap(path, coder, ins.pop(), outs[0], tuple(nodes)))
    names = [t.x for t in taps] + [t.codes for t in taps]
    if len(set(names)) != len(names):
        raise CoderNotFound("two coders share a scope in the graph (name the modules apart)")
    return taps


def picks(tap: CoderTap) -> list[str]:
    """The values of the coder's ``ArgMax`` nodes, one (rows, 1) int64 per OMP step in step
    order: the atom each step picked (also after a row stopped, when the pick is masked).
    :class:`CoderNotFound` unless there is one per non-zero."""
    out = [o for n in tap.nodes if n.op_type == "ArgMax" for o in n.output]
    if len(out) != tap.coder.n_nonzero:
        raise CoderNotFound(f"coder {tap.path!r}: {len(out)} ArgMax nodes for "
                            f"{tap.coder.n_nonzero} non-zeros")
    return out


def tapped(graph: onnx.ModelProto, taps: list[CoderTap], orders: bool = False,
           native: bool = False) -> onnx.ModelProto:
    """A copy of ``graph`` that also outputs each coder's images and codes (same nodes), and
    with ``orders`` each coder's picks (:func:`picks`) after them, coder by coder. With
    ``native`` the ``SparseCode`` nodes stay (the kernel library runs them; they have no
    picks to tap: their images and codes are the node's input and output)."""
    out = onnx.ModelProto()
    out.CopyFrom(graph if native else portable(graph, [(t.path, t.coder) for t in taps]))
    del out.metadata_props[:]
    for t in taps:
        out.graph.output.extend([helper.make_tensor_value_info(t.x, TensorProto.FLOAT, None),
                                 helper.make_tensor_value_info(t.codes, TensorProto.FLOAT, None)])
    if orders:
        out.graph.output.extend(helper.make_tensor_value_info(v, TensorProto.INT64, None)
                                for t in taps for v in picks(t))
    return out


def graph_order(picks: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """The graph's atoms in order (rows, n) from its picks (rows, n) (:func:`picks`), -1 after
    a row stopped (its picks beyond its non-zeros are masked)."""
    live = (codes != 0).sum(1)
    return np.where(np.arange(picks.shape[1])[None, :] < live[:, None], picks, -1)


def tap_session(graph: onnx.ModelProto, taps: list[CoderTap], native: bool = False):
    """onnxruntime on the :func:`tapped` copy of ``graph`` for ``taps``, with each coder's
    picks when every coder has one ``ArgMax`` per non-zero: ``(session, picks, names)``,
    ``picks`` per coder its :func:`picks` (None otherwise, and with ``native``: the kernel
    library runs the coders) and ``names`` the added outputs in order (per coder its images and
    codes, then every coder's picks)."""
    steps = None
    if not native:
        try:
            steps = [picks(t) for t in taps]
        except CoderNotFound:
            steps = None
    sess = session(tapped(graph, taps, orders=steps is not None, native=native)
                   .SerializeToString(), native=native)
    names = [v for t in taps for v in (t.x, t.codes)] + [v for p in steps or [] for v in p]
    return sess, steps, names


__all__ = ["CoderNotFound", "CoderTap", "coders", "find_coders", "picks", "portable", "tapped",
           "graph_order", "tap_session"]
