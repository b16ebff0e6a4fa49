"""The sparse coder's own graph: :class:`~tactile.training.sparse.SparseCoder` alone as ONNX.

Traced by the pinned exporter path (:func:`tactile.export.traced.trace_graph`, opset
:data:`tactile.contract.OPSET`) and constant-folded: the dictionary and its Gram matrix become
initializers. Inside a deployable graph the coder is traced with the rest of its model's
``post`` part instead (:mod:`tactile.export.graph`), as the same op types in the same order.
"""

from __future__ import annotations

import onnx
import torch

from tactile.export.traced import trace_graph
from tactile.training.sparse import SparseCoder


def coder_graph(coder: SparseCoder, batch: int = 2) -> onnx.ModelProto:
    """``coder`` as an ONNX model: input ``x`` (batch, features) float32 with a dynamic batch
    axis, output ``codes`` (batch, atoms) float32. ``batch`` is the example's (> 1, so that
    the tracer keeps the axis symbolic)."""
    x = torch.zeros(batch, coder.features)
    return trace_graph(coder, (x,), ["x"], ["codes"], {"x": {0: "batch"}, "codes": {0: "batch"}})


def coder_node_model(coder: SparseCoder, batch: int = 2) -> onnx.ModelProto:
    """``coder`` as one ``ai.tactile::SparseCode`` node (inputs ``x`` and the dictionary and
    Gram matrix as initializers, attribute ``n_nonzero``) whose model-local function holds
    :func:`coder_graph`'s graph (:mod:`tactile.export.custom_ops`). Same signature as
    :func:`coder_graph`'s model."""
    return coder_node(coder_graph(coder, batch), coder)


def coder_node(traced: onnx.ModelProto, coder: SparseCoder) -> onnx.ModelProto:
    """The one-node model of ``coder`` with ``traced`` (its :func:`coder_graph`) as fallback."""
    import numpy as np
    from onnx import helper, numpy_helper

    from tactile.contract import IR_VERSION
    from tactile.export.custom_ops import custom_node, function_of, opset_imports

    d = coder.dictionary.detach().float().numpy()
    gram = coder.gram.detach().float().numpy()
    body = onnx.GraphProto()
    body.CopyFrom(traced.graph)
    for name, value in (("dictionary", d), ("gram", gram)):  # the function's extra inputs
        vi = helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, list(value.shape))
        body.input.append(vi)
    fn = function_of("SparseCode", [([coder.features, coder.n_nonzero], body)])
    node = custom_node("SparseCode", ["x", "dictionary", "gram"], ["codes"], "coder",
                       n_nonzero=int(coder.n_nonzero))
    inits = [numpy_helper.from_array(np.ascontiguousarray(d), "dictionary"),
             numpy_helper.from_array(np.ascontiguousarray(gram), "gram")]
    graph = helper.make_graph([node], "coder", [traced.graph.input[0]], list(traced.graph.output),
                              initializer=inits)
    model = helper.make_model(graph, opset_imports=opset_imports(), functions=[fn])
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model, full_check=True)
    return model


__all__ = ["coder_graph", "coder_node", "coder_node_model"]
