"""The sparse coder's own graph: :class:`~tactile.training.sparse.SparseCoder` alone as ONNX.

Traced by the pinned exporter path (:func:`tactile.export.traced.trace_graph`, opset
:data:`tactile.contract.OPSET`) and constant-folded: the dictionary and its Gram matrix become
initializers. Inside a deployable graph the coder is traced with the rest of its model's
``post`` part instead (:mod:`tactile.export.graph`), as the same op types in the same order.
"""

from __future__ import annotations

from contextlib import contextmanager
from functools import partial

import onnx
import torch
from onnx import helper
from torch import Tensor

from tactile.contract import CUSTOM_DOMAIN as DOMAIN
from tactile.export.traced import trace_graph
from tactile.training.sparse import SparseCoder


def coder_graph(coder: SparseCoder, batch: int = 2) -> onnx.ModelProto:
    """``coder`` as an ONNX model: input ``x`` (batch, features) float32 with a dynamic batch
    axis, output ``codes`` (batch, atoms) float32. ``batch`` is the example's (> 1, so that
    the tracer keeps the axis symbolic)."""
    x = torch.zeros(batch, coder.features)
    return trace_graph(coder, (x,), ["x"], ["codes"], {"x": {0: "batch"}, "codes": {0: "batch"}})


class _SparseCodeOp(torch.autograd.Function):
    """A coder's codes in eager torch; one ``ai.tactile::SparseCode`` node when traced."""

    @staticmethod
    def forward(ctx, x: Tensor, dictionary: Tensor, gram: Tensor, n_nonzero: int,
                variant: int) -> Tensor:
        # the codes' own steps stay out of the trace (they read buffers that are not this
        # function's inputs): the traced graph holds the one node of symbolic()
        state = torch._C._get_tracing_state()
        torch._C._set_tracing_state(None)
        try:
            return _TRACED[variant].encode(x)[0]
        finally:
            torch._C._set_tracing_state(state)

    @staticmethod
    def symbolic(g, x, dictionary, gram, n_nonzero: int, variant: int):
        out = g.op(f"{DOMAIN}::SparseCode", x, dictionary, gram, n_nonzero_i=n_nonzero,
                   variant_i=variant)
        sizes = x.type().varyingSizes() if x.type().dim() is not None else None
        rows = sizes[0] if sizes else None
        out.setType(x.type().with_sizes([rows, int(dictionary.type().sizes()[0])]))
        return out


_TRACED: dict[int, SparseCoder] = {}


@contextmanager
def coders_as_nodes(module: torch.nn.Module):
    """While tracing ``module``, each :class:`SparseCoder` in it becomes one ``SparseCode``
    node (attribute ``variant``: its index among them, in module order) instead of its OMP
    steps. Yields the coders, in ``variant`` order."""
    coders = [m for m in module.modules() if isinstance(m, SparseCoder)]
    for k, coder in enumerate(coders):
        _TRACED[k] = coder
        coder.forward = partial(_coded, coder, k)
    try:
        yield coders
    finally:
        for coder in coders:
            del coder.forward
        _TRACED.clear()


def _coded(coder: SparseCoder, variant: int, x: Tensor) -> Tensor:
    return _SparseCodeOp.apply(x, coder.dictionary.to(x.dtype), coder.gram.to(x.dtype),
                               coder.n_nonzero, variant)


def coder_function(coders: list[SparseCoder]) -> onnx.FunctionProto:
    """The model-local ``SparseCode`` function of ``coders`` (body ``variant`` is
    :func:`coder_graph` of ``coders[variant]``)."""
    from tactile.export.custom_ops import function_of

    variants = []
    for k, coder in enumerate(coders):
        body = onnx.GraphProto()
        body.CopyFrom(coder_graph(coder).graph)
        for name, shape in (("dictionary", [coder.atoms, coder.features]),
                            ("gram", [coder.atoms, coder.atoms])):  # the function's inputs
            body.input.append(helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, shape))
        variants.append(([coder.features, coder.n_nonzero, k], body))
    return function_of("SparseCode", variants)


def coder_node_model(coder: SparseCoder, batch: int = 2) -> onnx.ModelProto:
    """``coder`` as one ``ai.tactile::SparseCode`` node (inputs ``x`` and the dictionary and
    Gram matrix as initializers, attribute ``n_nonzero``) whose model-local function holds
    :func:`coder_graph`'s graph (:mod:`tactile.export.custom_ops`). Same signature as
    :func:`coder_graph`'s model."""
    return coder_node(coder_graph(coder, batch), coder)


def coder_node(traced: onnx.ModelProto, coder: SparseCoder) -> onnx.ModelProto:
    """The one-node model of ``coder`` with ``traced`` (its :func:`coder_graph`) as fallback."""
    import numpy as np
    from onnx import numpy_helper

    from tactile.contract import IR_VERSION
    from tactile.export.custom_ops import custom_node, opset_imports

    d = coder.dictionary.detach().float().numpy()
    gram = coder.gram.detach().float().numpy()
    fn = coder_function([coder])
    node = custom_node("SparseCode", ["x", "dictionary", "gram"], ["codes"], "coder",
                       n_nonzero=int(coder.n_nonzero), variant=0)
    inits = [numpy_helper.from_array(np.ascontiguousarray(d), "dictionary"),
             numpy_helper.from_array(np.ascontiguousarray(gram), "gram")]
    graph = helper.make_graph([node], "coder", [traced.graph.input[0]], list(traced.graph.output),
                              initializer=inits)
    model = helper.make_model(graph, opset_imports=opset_imports(), functions=[fn])
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model, full_check=True)
    return model


__all__ = ["coder_function", "coder_graph", "coder_node", "coder_node_model", "coders_as_nodes"]
