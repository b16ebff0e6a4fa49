"""Wiring ONNX graphs together: rename every value of a graph (subgraphs included), then join.

A uniform renaming (a prefix, except for the names wired to another graph) keeps the meaning of
``Loop`` bodies that read values of the enclosing scope, because every scope is renamed the same
way. ``onnx.compose`` is not used: the renaming here is all the composition needs, and it is
small enough to read.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import onnx
from onnx import helper


def renamed(model: onnx.ModelProto, prefix: str, wire: dict[str, str]) -> onnx.GraphProto:
    """A copy of ``model``'s graph with name ``v`` -> ``wire.get(v, prefix + v)`` everywhere."""
    graph = onnx.GraphProto()
    graph.CopyFrom(model.graph)
    _rename_graph(graph, lambda v: v if not v else wire.get(v, prefix + v), prefix)
    return graph


def _rename_graph(g: onnx.GraphProto, name: Callable[[str], str], prefix: str) -> None:
    for node in g.node:
        node.name = prefix + node.name if node.name else ""  # unnamed nodes stay unnamed
        node.input[:] = [name(v) for v in node.input]
        node.output[:] = [name(v) for v in node.output]
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                _rename_graph(attr.g, name, prefix)
            for sub in attr.graphs:
                _rename_graph(sub, name, prefix)
    for seq in (g.input, g.output, g.value_info):
        for vi in seq:
            vi.name = name(vi.name)
    for init in g.initializer:
        init.name = name(init.name)
    for sparse in g.sparse_initializer:
        sparse.values.name = name(sparse.values.name)


def join(
    parts: Sequence[onnx.GraphProto],
    inputs: Sequence[onnx.ValueInfoProto],
    outputs: Sequence[onnx.ValueInfoProto],
    opset: int,
    name: str,
) -> onnx.ModelProto:
    """One model from already-renamed graphs, in execution order, with the given signature."""
    nodes, inits = [], []
    for g in parts:
        nodes += list(g.node)
        inits += list(g.initializer)
    graph = helper.make_graph(nodes, name, list(inputs), list(outputs), initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
    return model


def value_info(model: onnx.ModelProto, names: Sequence[str]) -> list[onnx.ValueInfoProto]:
    """The graph inputs/outputs of ``model`` called ``names`` (copies), in that order."""
    found = {vi.name: vi for vi in [*model.graph.input, *model.graph.output]}
    out = []
    for n in names:
        vi = onnx.ValueInfoProto()
        vi.CopyFrom(found[n])
        out.append(vi)
    return out
