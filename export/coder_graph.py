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


__all__ = ["coder_graph"]
