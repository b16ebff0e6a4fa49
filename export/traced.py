"""Tracing torch code to ONNX, and the graph surgery the hand-built graphs need.

The pinned exporter path: ``torch.onnx.export(..., dynamo=False)`` (the TorchScript exporter)
at opset :data:`tactile.contract.OPSET` (:func:`export_traced`, the project's one call of it).
:func:`trace_graph` traces a function and then folds it: ``onnxscript.optimizer``, then our own
passes (constants evaluated, the exporter's no-op ``Slice`` on scatter sources dropped,
constant operands of broadcasting nodes given the output's rank). :func:`inline` copies a
traced model's nodes into an enclosing graph under a name prefix, and :func:`loop_body` wraps
nodes into an ONNX ``Loop`` body: the EMD graph (:mod:`tactile.export.emd_graph`) is wired
from traced pieces with them.
"""

from __future__ import annotations

import io
import logging
import warnings
from collections.abc import Callable, Sequence

import numpy as np
import onnx
import onnxscript.optimizer
import torch
from onnx import TensorProto, helper, numpy_helper
from onnx.reference import ReferenceEvaluator
from torch import Tensor, nn

from tactile.contract import OPSET


class _Fn(nn.Module):
    """Wrap a function so the tracer sees a module."""

    def __init__(self, fn: Callable[..., tuple[Tensor, ...]]) -> None:
        super().__init__()
        self.fn = fn

    def forward(self, *args: Tensor) -> tuple[Tensor, ...]:
        return self.fn(*args)


def export_traced(
    module: nn.Module,
    args: Sequence[Tensor],
    inputs: Sequence[str],
    outputs: Sequence[str],
    dynamic: dict[str, dict[int, str]],
) -> onnx.ModelProto:
    """``module`` traced to ONNX by the pinned exporter path (TorchScript, opset :data:`OPSET`).

    The one place the project calls ``torch.onnx.export``: the EMD pieces
    (:mod:`tactile.export.emd_graph`), the sparse coder (:mod:`tactile.export.coder_graph`) and
    the deployable graph (:mod:`tactile.export.graph`) are all traced here.
    """
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
        torch.onnx.export(
            module,
            tuple(args),
            buf,
            dynamo=False,
            opset_version=OPSET,
            input_names=list(inputs),
            output_names=list(outputs),
            dynamic_axes=dynamic,
            do_constant_folding=True,
        )
    return onnx.load_from_string(buf.getvalue())


def trace_graph(
    fn: Callable[..., tuple[Tensor, ...]],
    args: Sequence[Tensor],
    inputs: Sequence[str],
    outputs: Sequence[str],
    dynamic: dict[str, dict[int, str]],
) -> onnx.ModelProto:
    """Trace ``fn`` to a constant-folded ONNX model (the pinned exporter path)."""
    traced = export_traced(_Fn(fn), args, inputs, outputs, dynamic)
    folder = logging.getLogger("onnxscript.optimizer._constant_folding")
    folder.addFilter(_folded_if_shapes)
    try:
        model = onnxscript.optimizer.optimize(traced)
    finally:
        folder.removeFilter(_folded_if_shapes)
    return _rank_constants(_drop_update_slices(_fold_constants(model)))


def _folded_if_shapes(record: logging.LogRecord) -> bool:
    """Drop only the optimizer's "cannot merge shapes" warning, keep every other record.

    The exporter wraps a scatter with a reduction in ``If`` nodes for 0-d inputs. The optimizer
    folds them away (ours have rank 3), warning on the way that the 0-d branch's flattened
    shape does not merge with the result's: harmless, the branch is gone, but it would reach
    the log of everyone who exports a model.
    """
    return "Cannot merge shapes" not in record.getMessage()


def _drop_update_slices(model: onnx.ModelProto) -> onnx.ModelProto:
    """Remove the ``Shape``/``Slice`` pair the exporter puts on every ``scatter_add`` source.

    It trims the source to the index's shape; in this package they always have equal shapes
    (asserted by the eager code paths), so the pair is a no-op costing two kernels per call.
    """
    graph = model.graph
    producer = {o: node for node in graph.node for o in node.output}
    drop: set[int] = set()
    for node in graph.node:
        if node.op_type != "ScatterElements":
            continue
        sl = producer.get(node.input[2])
        if sl is None or sl.op_type != "Slice" or len(sl.input) < 3:
            continue
        shape = producer.get(sl.input[2])
        if shape is None or shape.op_type != "Shape" or shape.input[0] != node.input[1]:
            continue
        node.input[2] = sl.input[0]
        drop.update((id(sl), id(shape)))
    users = {v for node in graph.node if id(node) not in drop for v in node.input}
    kept = [n for n in graph.node if id(n) not in drop or any(o in users for o in n.output)]
    del graph.node[:]
    graph.node.extend(kept)
    _drop_unused_initializers(graph)
    return model


def _drop_unused_initializers(graph: onnx.GraphProto) -> None:
    """Remove the initializers no node (nor any subgraph of one) reads."""
    used = {v for n in graph.node for v in n.input}
    used |= {v for n in graph.node for v in _subgraph_inputs(n)}
    inits = [init for init in graph.initializer if init.name in used]
    del graph.initializer[:]
    graph.initializer.extend(inits)


def _fold_constants(model: onnx.ModelProto) -> onnx.ModelProto:
    """Evaluate every node whose inputs are all initializers, keeping only the result.

    The TorchScript exporter builds ``Pad``'s pads (and a few constants) from small chains of
    ``ConstantOfShape``/``Concat``/``Reshape``/``Transpose`` nodes that the optimizer leaves
    in place; each would cost a kernel launch per sift.
    """
    graph = model.graph
    known = {init.name: numpy_helper.to_array(init) for init in graph.initializer}
    kept = []
    for node in graph.node:
        has_graph = any(a.type == onnx.AttributeProto.GRAPH for a in node.attribute)
        if (
            not has_graph
            and node.op_type not in ("Shape", "Size")
            and node.input
            and all(v in known for v in node.input if v)
        ):
            inputs = [v for v in node.input if v]
            values = ReferenceEvaluator(_single_node(node, inputs, known)).run(
                None, {v: known[v] for v in inputs}
            )
            for out, val in zip(node.output, values):
                known[out] = np.asarray(val)
            continue
        kept.append(node)
    used = {v for node in kept for v in node.input} | {o.name for o in graph.output}
    used |= {v for node in kept for v in _subgraph_inputs(node)}
    del graph.node[:]
    graph.node.extend(kept)
    del graph.initializer[:]
    inits = [numpy_helper.from_array(known[v], v) for v in sorted(known) if v in used]
    graph.initializer.extend(inits)
    return model


_BROADCASTING = {
    "Add", "Sub", "Mul", "Div", "Pow", "Max", "Min", "Mod", "Equal", "Less", "LessOrEqual",
    "Greater", "GreaterOrEqual", "And", "Or", "Xor", "Where",
}


def _rank_constants(model: onnx.ModelProto) -> onnx.ModelProto:
    """Give every constant operand of a broadcasting node the rank of the node's output.

    The tracer writes scalars as 0-d tensors. onnxruntime's CPU kernels broadcast a 0-d
    operand against a tensor with size-1 axes (the (2, R, 2, 1)-shaped boundary quantities,
    ``j1`` of shape (2, R, 1)) one element at a time, about 10 ns an element, but a constant of
    shape (1, ..., 1) at full speed (about 0.1 ns): at 2,048 rows that is 40 us against 0.4 us
    per node. Leading size-1 axes change nothing in the arithmetic (numpy broadcasting).
    """
    graph = model.graph
    inferred = onnx.shape_inference.infer_shapes(model).graph
    rank = {
        v.name: len(v.type.tensor_type.shape.dim)
        for v in [*inferred.value_info, *inferred.output, *inferred.input]
        if v.type.tensor_type.HasField("shape")
    }
    known = {init.name: init for init in graph.initializer}
    added: dict[str, onnx.TensorProto] = {}
    for node in graph.node:
        if node.op_type not in _BROADCASTING or node.output[0] not in rank:
            continue
        r = rank[node.output[0]]
        for i, v in enumerate(node.input):
            init = known.get(v)
            if init is None or len(init.dims) >= r:
                continue
            new = f"{v}_rank{r}"
            if new not in added:
                arr = numpy_helper.to_array(init)
                shaped = arr.reshape((1,) * (r - arr.ndim) + arr.shape)
                added[new] = numpy_helper.from_array(shaped, new)
            node.input[i] = new
    graph.initializer.extend(added.values())
    _drop_unused_initializers(graph)
    return model


def _single_node(node: onnx.NodeProto, inputs: list[str], known: dict) -> onnx.ModelProto:
    """A model of ``node`` alone, its ``inputs`` typed as their values in ``known``."""
    ins = [
        helper.make_tensor_value_info(v, helper.np_dtype_to_tensor_dtype(known[v].dtype), None)
        for v in inputs
    ]
    outs = [helper.make_tensor_value_info(v, TensorProto.UNDEFINED, None) for v in node.output]
    g = helper.make_graph([node], "fold", ins, outs)
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", OPSET)])


def _subgraph_inputs(node: onnx.NodeProto) -> set[str]:
    """The values ``node``'s subgraphs (nested ones included) read."""
    names: set[str] = set()
    for attr in node.attribute:
        if attr.type == onnx.AttributeProto.GRAPH:
            for inner in attr.g.node:
                names.update(inner.input)
                names |= _subgraph_inputs(inner)
    return names


def inline(
    model: onnx.ModelProto, prefix: str, rename: dict[str, str]
) -> tuple[list[onnx.NodeProto], list[onnx.TensorProto]]:
    """Nodes and initializers of ``model`` with every internal name prefixed.

    ``rename`` maps the model's input and output names to names in the enclosing graph.
    """

    def name(v: str) -> str:
        return v if not v else rename.get(v, prefix + v)

    def rename_graph(graph: onnx.GraphProto) -> None:
        for value in [*graph.input, *graph.output, *graph.value_info]:
            value.name = name(value.name)
        for init in graph.initializer:
            init.name = name(init.name)
        for node in graph.node:
            node.name = prefix + node.name
            node.input[:] = [name(v) for v in node.input]
            node.output[:] = [name(v) for v in node.output]
            for attr in node.attribute:
                if attr.type == onnx.AttributeProto.GRAPH:
                    rename_graph(attr.g)

    nodes = []
    for node in model.graph.node:
        new = onnx.NodeProto()
        new.CopyFrom(node)
        nodes.append(new)
    holder = helper.make_graph(nodes, "holder", [], [])
    rename_graph(holder)
    nodes = list(holder.node)
    inits = []
    for init in model.graph.initializer:
        new = onnx.TensorProto()
        new.CopyFrom(init)
        new.name = name(init.name)
        inits.append(new)
    return nodes, inits


def tensor_info(name: str, elem: int, shape: list) -> onnx.ValueInfoProto:
    """A tensor's value info: ``elem`` an ONNX element type, ``shape`` sizes and axis names."""
    return helper.make_tensor_value_info(name, elem, shape)


def loop_body(
    name: str,
    prefix: str,
    nodes: list[onnx.NodeProto],
    carried: list[tuple[str, int, list]],
    scans: Sequence[tuple[str, int, list]] = (),
    cond_out: bool = False,
) -> onnx.GraphProto:
    """An ONNX ``Loop`` body around ``nodes``.

    Inputs: ``{prefix}_i`` (iteration), ``{prefix}_c`` (condition), then the ``carried``
    values (name, element type, shape); outputs: the condition (passed through unless
    ``cond_out``: then ``nodes`` compute ``{prefix}_c_out``), each carried value as
    ``{name}_out``, then the ``scans`` (one entry per iteration).
    """
    cond = f"{prefix}_c"
    keep = [] if cond_out else [helper.make_node("Identity", [cond], [f"{cond}_out"])]
    return helper.make_graph(
        [*nodes, *keep],
        name,
        [tensor_info(f"{prefix}_i", TensorProto.INT64, []), tensor_info(cond, TensorProto.BOOL, []),
         *[tensor_info(*v) for v in carried]],
        [tensor_info(f"{cond}_out", TensorProto.BOOL, []),
         *[tensor_info(f"{n}_out", e, shape) for n, e, shape in carried],
         *[tensor_info(*v) for v in scans]],
    )


def keep_used_initializers(nodes: list[onnx.NodeProto], inits: list[onnx.TensorProto]) -> None:
    """Keep only the initializers ``nodes`` read (in place)."""
    used = {v for n in nodes for v in n.input}
    inits[:] = [i for i in inits if i.name in used]


__all__ = ["export_traced", "inline", "keep_used_initializers", "loop_body", "tensor_info",
           "trace_graph"]
