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
    functions: Sequence[onnx.FunctionProto] = (),
) -> onnx.ModelProto:
    """One model from already-renamed graphs, in execution order, with the given signature;
    with ``functions`` (the ``ai.tactile`` ops' fallbacks) also those and their domain."""
    nodes, inits = [], []
    for g in parts:
        nodes += list(g.node)
        inits += list(g.initializer)
    graph = helper.make_graph(nodes, name, list(inputs), list(outputs), initializer=inits)
    opsets = [helper.make_opsetid("", opset)]
    if functions:
        opsets.append(helper.make_opsetid(functions[0].domain, 1))
    model = helper.make_model(graph, opset_imports=opsets, functions=list(functions))
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


def outer_names(g: onnx.GraphProto) -> set[str]:
    """Values a graph reads but does not make: its enclosing scopes' (subgraphs included)."""
    made = {i.name for i in g.input} | {i.name for i in g.initializer}
    used: set[str] = set()
    for node in g.node:
        used.update(v for v in node.input if v)
        for attr in node.attribute:
            for sub in ([attr.g] if attr.type == onnx.AttributeProto.GRAPH else []) + list(
                    attr.graphs):
                used |= outer_names(sub)
        made.update(node.output)
    return used - made


def toposorted(model: onnx.ModelProto) -> onnx.ModelProto:
    """``model`` with its top-level nodes in an order where every value, including those a
    ``Loop``/``If`` body reads from the enclosing graph, is made before it is read (stable:
    nodes keep their order where they can). Some optimisers order by explicit inputs only."""
    g = model.graph
    nodes = list(g.node)
    needs = []
    for node in nodes:
        deps = {v for v in node.input if v}
        for attr in node.attribute:
            for sub in ([attr.g] if attr.type == onnx.AttributeProto.GRAPH else []) + list(
                    attr.graphs):
                deps |= outer_names(sub)
        needs.append(deps)
    producer = {o: i for i, n in enumerate(nodes) for o in n.output if o}
    done: set[int] = set()
    order: list[int] = []
    while len(order) < len(nodes):
        progress = False
        for i in range(len(nodes)):
            if i in done:
                continue
            if all(producer.get(v, -1) in done or v not in producer for v in needs[i]):
                order.append(i)
                done.add(i)
                progress = True
        if not progress:
            raise ValueError("the graph has a cycle")
    del g.node[:]
    g.node.extend(nodes[i] for i in order)
    return model
