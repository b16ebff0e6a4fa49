"""The toolkit's own ONNX ops: one ``ai.tactile`` node per EMD and per sparse coder, each with a
model-local function (FunctionProto) of the same domain and name holding its portable graph.

onnxruntime resolves a node against the schemas registered with it first: with the native
kernel library registered (``tactile/native/ort_ops.c``, ``RegisterCustomOps``) the node runs
the C kernel; without it onnxruntime expands the model-local function, whose body is the
standard-op graph the exporter wrote before these ops existed (``docs/export.md``). So one file
runs on any onnxruntime, and faster where the library is there.

Ops (version 1 of domain :data:`DOMAIN`):

``EMD(x_in) -> imfs, residue, n_valid``, attributes ``n_imfs``, ``n_sifts``
    x_in (batch, channels, time) float32; imfs (batch, channels, n_imfs, time); residue
    (batch, channels, time); n_valid (batch, channels) int64 (:mod:`tactile.export.emd_graph`).
``SparseCode(x, dictionary, gram) -> codes``, attributes ``n_nonzero``, ``variant``
    x (rows, features), dictionary (atoms, features), gram (atoms, atoms), codes (rows, atoms),
    float32 (:mod:`tactile.export.coder_graph`).

A function is one per (domain, name) in a model, while a model may hold EMDs of several
window shapes and settings (one body each): the function then picks its body with ``If`` nodes
on the input's (channels, time) and the node's attributes (:func:`function_of`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from tactile.contract import CUSTOM_DOMAIN, OPSET

DOMAIN = CUSTOM_DOMAIN
VERSION = 1
ATTRIBUTES = {"EMD": ("n_imfs", "n_sifts"), "SparseCode": ("n_nonzero", "variant")}
"""Each op's integer attributes, in the order :func:`function_of`'s keys give them. A
SparseCode's ``variant`` (its index among the model's coders) only picks the fallback body
that holds its dictionary; the kernel reads the dictionary from its inputs and ignores it."""


def _body_nodes(graph: onnx.GraphProto, prefix: str, wire: dict[str, str]) -> list:
    """``graph``'s nodes with its initializers as ``Constant`` nodes (a function has no
    initializers), every value renamed ``prefix + name`` except the ``wire``d ones."""
    from tactile.export.compose import renamed

    model = helper.make_model(graph)
    g = renamed(model, prefix, wire)
    consts = [helper.make_node("Constant", [], [init.name], value=init) for init in g.initializer]
    return consts + list(g.node)


def function_of(
    op: str,
    variants: Sequence[tuple[Sequence[int], onnx.GraphProto]],
) -> onnx.FunctionProto:
    """The model-local function ``ai.tactile::op``: its inputs and outputs are the portable
    graphs' (all alike in names and types), its body the one graph, or with several an ``If``
    chain picking the graph whose key matches ``[shape of input 0 from axis 1..., attributes]``
    (the last variant serves any other key; it is never reached from the exporter's nodes)."""
    first = variants[0][1]
    ins = [i.name for i in first.input]
    outs = [o.name for o in first.output]
    attrs = list(ATTRIBUTES[op])
    wire = {n: n for n in ins + outs}
    opsets = [helper.make_opsetid("", OPSET)]
    if len(variants) == 1:
        return helper.make_function(DOMAIN, op, ins, outs, _body_nodes(first, "", wire), opsets,
                                    attributes=attrs)
    nodes = [
        helper.make_node("Constant", [], ["key/axis0"],
                         value=numpy_helper.from_array(np.array([0], np.int64))),
        helper.make_node("Shape", [ins[0]], ["key/shape"], start=1),
    ]
    for a in attrs:
        ref = onnx.AttributeProto()  # the node's attribute, as a value of the body
        ref.name, ref.ref_attr_name, ref.type = "value_int", a, onnx.AttributeProto.INT
        nodes.append(helper.make_node("Constant", [], [f"key/{a}"]))
        nodes[-1].attribute.append(ref)
        nodes.append(helper.make_node("Unsqueeze", [f"key/{a}", "key/axis0"], [f"key/{a}_1"]))
    nodes.append(helper.make_node("Concat", ["key/shape", *(f"key/{a}_1" for a in attrs)],
                                  ["key"], axis=0))
    chain, names = _pick(variants, 0, ins, outs)
    nodes += chain
    nodes += [helper.make_node("Identity", [v], [o]) for v, o in zip(names, outs, strict=True)]
    return helper.make_function(DOMAIN, op, ins, outs, nodes, opsets, attributes=attrs)


def _pick(variants, k: int, ins: list[str], outs: list[str]) -> tuple[list, list[str]]:
    """Nodes computing variant ``k``'s graph if the key matches it, else the later variants'
    (the last one unconditionally), and the names of their outputs."""
    key, graph = variants[k]
    mine = [f"v{k}/{o}" for o in outs]
    body = _body_nodes(graph, f"v{k}/", {n: n for n in ins} | dict(zip(outs, mine, strict=True)))
    if k == len(variants) - 1:
        return body, mine
    rest, rest_names = _pick(variants, k + 1, ins, outs)
    want = numpy_helper.from_array(np.asarray(key, np.int64))
    picked = [f"sel{k}/{o}" for o in outs]
    nodes = [
        helper.make_node("Constant", [], [f"v{k}/key"], value=want),
        helper.make_node("Equal", ["key", f"v{k}/key"], [f"v{k}/eq"]),
        helper.make_node("Cast", [f"v{k}/eq"], [f"v{k}/eq_i"], to=TensorProto.INT64),
        helper.make_node("ReduceMin", [f"v{k}/eq_i"], [f"v{k}/all"], keepdims=0),
        helper.make_node("Cast", [f"v{k}/all"], [f"v{k}/match"], to=TensorProto.BOOL),
        helper.make_node("If", [f"v{k}/match"], picked,
                         then_branch=_branch(f"variant{k}", body, graph, mine),
                         else_branch=_branch(f"after{k}", rest, graph, rest_names)),
    ]
    return nodes, picked


def _branch(name: str, nodes: list, graph: onnx.GraphProto, names: list[str]) -> onnx.GraphProto:
    """A subgraph of ``nodes`` with outputs ``names`` (the types of ``graph``'s outputs)."""
    out_info = []
    for o, n in zip(graph.output, names, strict=True):
        vi = onnx.ValueInfoProto()
        vi.name = n
        vi.type.tensor_type.elem_type = o.type.tensor_type.elem_type
        out_info.append(vi)
    return helper.make_graph(nodes, name, [], out_info)


def variant_body(fn: onnx.FunctionProto, k: int) -> tuple[list, list[str]]:
    """Variant ``k``'s body in ``fn`` (made by :func:`function_of`): its nodes (reading the
    function's inputs by name) and the names of its outputs, in the function's order."""
    if not any(n.op_type == "If" and n.output[0].startswith("sel0/") for n in fn.node):
        return list(fn.node), list(fn.output)  # one variant: the body itself
    names = [f"v{k}/{o}" for o in fn.output]
    todo = [n for n in fn.node if n.op_type == "If"]
    while todo:
        node = todo.pop()
        for attr in node.attribute:
            g = attr.g
            if [o.name for o in g.output] == names:
                return list(g.node), names
            todo += [n for n in g.node if n.op_type == "If"]
    raise ValueError(f"{fn.name}: no variant {k}")


def custom_node(op: str, inputs: Sequence[str], outputs: Sequence[str], name: str,
                **attrs: int) -> onnx.NodeProto:
    """One ``ai.tactile`` node (attributes as :data:`ATTRIBUTES` lists them)."""
    if sorted(attrs) != sorted(ATTRIBUTES[op]):
        raise ValueError(f"{op} takes attributes {ATTRIBUTES[op]}, got {sorted(attrs)}")
    return helper.make_node(op, list(inputs), list(outputs), name=name, domain=DOMAIN, **attrs)


def custom_nodes(model: onnx.ModelProto) -> list[dict]:
    """The ``ai.tactile`` nodes of ``model``'s main graph: ``{op, name, attributes}`` each, in
    graph order (what the contract's ``custom_ops`` key records)."""
    out = []
    for node in model.graph.node:
        if node.domain == DOMAIN:
            attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
            out.append({"op": node.op_type, "name": node.name, "attributes": attrs})
    return out


def custom_ops_key(model: onnx.ModelProto) -> str:
    """The contract's ``custom_ops`` value for ``model`` (JSON): its nodes and their fallback."""
    import json

    return json.dumps({"domain": DOMAIN, "version": VERSION, "nodes": custom_nodes(model),
                       "fallback": "model-local function of the same domain and name "
                                   "(standard ONNX ops)"}, sort_keys=True)


def opset_imports() -> list[onnx.OperatorSetIdProto]:
    """The default domain at :data:`OPSET` and ``ai.tactile`` at :data:`VERSION`."""
    return [helper.make_opsetid("", OPSET), helper.make_opsetid(DOMAIN, VERSION)]


__all__ = ["ATTRIBUTES", "DOMAIN", "VERSION", "custom_node", "custom_nodes", "custom_ops_key",
           "function_of",
           "opset_imports", "variant_body"]
