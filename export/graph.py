"""The deployable graph: raw window + state in, class probabilities + new state out.

Exporter path (pinned): ``torch.onnx.export(..., dynamo=False)`` (the TorchScript exporter) at
opset :data:`tactile.contract.OPSET` (18), with an example batch of 3 and ``batch`` declared
dynamic. It captures ``nn.LSTM`` as ONNX ``LSTM`` nodes with a symbolic batch, and it is the path
the EMD graph is built with, so both halves share one exporter.

Any model whose ``pre`` has the three-stage interface (``emds``, ``normalise``, ``emd_inputs``,
``finish``; :class:`tactile.training.model.Preprocess` and the granular preprocessing) and whose
``head`` maps ``(features, h, c) -> (logits, h, c)`` is exported. Without EMDs the whole model is
one export. With them the graph is composed of parts, because each EMD is assembled by hand
with ``Loop`` nodes (:func:`tactile.export.emd_graph.portable_body`) rather than
traced::

    x (B, T, C) -> [pre: normalise, emd_inputs] -> z (B, T, C), emd0_in (B, n_0, L_0), ...
    emdk_in -> [EMD node k: its own IMFs, sifts, length; float64 inside] -> imfsk (B, n_k, K_k, L_k)
    z, imfs0.., h, c -> [post: finish (features, sparse codes), head, softmax] -> probs, h, c

``pre`` and ``post`` reuse the trained model's own modules; the export-time parity check
compares the composed graph with the model's ``forward`` itself (its EMDs in float64, as
training's feature pass computed them), so a drift between this split
and the training code fails the export.
"""

from __future__ import annotations

from contextlib import contextmanager

import onnx
import torch
from torch import Tensor, nn

import tactile
from tactile.contract import BATCH, INPUTS, IR_VERSION, OPSET, OUTPUTS
from tactile.export.coder_graph import coder_function, coders_as_nodes
from tactile.export.compose import join, renamed, value_info
from tactile.export.custom_ops import DOMAIN, custom_node, function_of, opset_imports
from tactile.export.emd_graph import portable_body
from tactile.export.traced import export_traced
from tactile.training.model import Blend

EXAMPLE_BATCH = 3
"""Example batch of the traced export: > 1, so that the tracer cannot fix the batch size."""
EXPORTER = f"torch.onnx.export dynamo=False (TorchScript), opset {OPSET}"

_STATE_AXES = {1: BATCH}


class _Pre(nn.Module):
    """x (B, T, C) in units -> z (B, T, C) and one (B, n_k, L_k) input per EMD of ``pre``."""

    def __init__(self, pre: nn.Module) -> None:
        super().__init__()
        self.pre = pre
        # the wrapper's mode is the model's: the exporter restores the wrapper's mode, with
        # its children's, after tracing (a new module is in training mode)
        self.train(pre.training)

    def forward(self, x: Tensor) -> tuple[Tensor, ...]:
        z = self.pre.normalise(x)
        return (z, *self.pre.emd_inputs(z))


class _Post(nn.Module):
    """z, imfs_0..imfs_{k-1} (B, n_k, K_k, L_k), h, c (L, B, H) -> probs (B, classes), h, c."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.pre, self.head = model.pre, model.head
        self.n_emd = len(model.pre.emds)
        self.train(model.training)  # as _Pre

    def forward(self, z: Tensor, *rest: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        imfs, (h, c) = list(rest[: self.n_emd]), rest[self.n_emd :]
        logits, h, c = self.head(self.pre.finish(z, imfs), h, c)
        return torch.softmax(logits, dim=1), h, c


def split_forward(model: nn.Module, x: Tensor, h: Tensor, c: Tensor):
    """The composed graph's computation in eager torch (pre, torch EMDs, post), for tests."""
    z, *sel = _Pre(model.pre)(x)
    imfs = [emd(s)[0] for emd, s in zip(model.pre.emds, sel, strict=True)]
    return _Post(model)(z, *imfs, h, c)


trace = export_traced  # the pinned exporter path, shared with the EMD graph


def example_input(model: nn.Module, batch: int = EXAMPLE_BATCH, seed: int = 0) -> Tensor:
    """(batch, window, C) float32 windows in units: N(mean, std) of the training split.

    Uses the pre's ``mean`` and ``std`` buffers (C,) (every preprocessing module has them).
    """
    pre = model.pre
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(batch, model.cfg.window, int(pre.mean.numel()), generator=g)
    return z * pre.std + pre.mean


def build_graph(model: nn.Module) -> onnx.ModelProto:
    """The float32 graph of ``model`` (no metadata yet), checked by ``onnx.checker``.

    Inputs ``x`` (batch, window, channels), ``h``, ``c`` (layers, batch, hidden); outputs
    ``probs`` (batch, classes), ``h_out``, ``c_out`` (layers, batch, hidden).
    """
    model = model.eval().float()
    x = example_input(model)
    h, c = model.zero_state(EXAMPLE_BATCH)
    state = {"h": _STATE_AXES, "c": _STATE_AXES, "h_out": _STATE_AXES, "c_out": _STATE_AXES}
    with torch.no_grad(), coders_as_nodes(model) as coders, _idle_blend_left_out(model):
        if not len(model.pre.emds):
            out = trace(model, [x, h, c], INPUTS, OUTPUTS,
                        {"x": {0: BATCH}, "probs": {0: BATCH}, **state})
        else:
            out = _compose(model, x, h, c, state)
    # the coders' own graphs, traced as they are (outside coders_as_nodes)
    out = _with_functions(out, [coder_function(coders)] if coders else [])
    out.ir_version = IR_VERSION
    out.producer_name = "tactile.export"
    out.producer_version = tactile.__version__
    onnx.checker.check_model(out, full_check=True)
    return out


@contextmanager
def _idle_blend_left_out(model: nn.Module):
    """While tracing ``model``, a blended head whose mix is 0 is its LSTM alone: the mix's
    output, ``log_softmax`` of the LSTM's logits, gives the same probabilities, and the
    regression would be computed for nothing (0.011 ms a window, ``training.md``); so would a
    granular model's window features, which only the regression reads. Parity is still
    checked against the model as trained, blend and all."""
    head = getattr(model, "head", None)
    if not (isinstance(head, Blend) and float(head.mix) == 0.0):
        yield
        return
    window_features = getattr(model.pre, "window_features", None)
    model.head = head.recurrent
    if window_features is not None:
        model.pre.window_features = None
    try:
        yield
    finally:
        model.head = head
        if window_features is not None:
            model.pre.window_features = window_features


def _with_functions(model: onnx.ModelProto, functions: list) -> onnx.ModelProto:
    """``model`` with more ``ai.tactile`` functions and the domain's opset import (none: as it
    is); its coder nodes named ``coder<variant>``."""
    if not functions and not model.functions:
        return model
    for node in model.graph.node:
        if node.domain == DOMAIN and node.op_type == "SparseCode":
            variant = next(a.i for a in node.attribute if a.name == "variant")
            node.name = f"coder{variant}"
    del model.opset_import[:]
    model.opset_import.extend(opset_imports())
    model.functions.extend(functions)
    return model


def _compose(model: nn.Module, x: Tensor, h: Tensor, c: Tensor, state: dict) -> onnx.ModelProto:
    """pre (traced) -> one ``ai.tactile::EMD`` node per entry of ``model.pre.emds`` (its Loop
    graph as the function's body) -> post (traced; its coders one ``SparseCode`` node each)."""
    pre_m = _Pre(model.pre)
    z, *sel = pre_m(x)
    emds = list(model.pre.emds)
    ins = [f"emd{k}_in" for k in range(len(emds))]
    outs = [f"imfs{k}" for k in range(len(emds))]
    batch = {0: BATCH}
    pre = trace(pre_m, [x], ["x"], ["z", *ins],
                {"x": batch, "z": batch, **dict.fromkeys(ins, batch)})
    graphs = [renamed(pre, "pre/", {"x": "x", "z": "z", **{n: n for n in ins}})]
    imfs, bodies, emd_nodes, shapes = [], {}, [], []
    for k, (emd, s) in enumerate(zip(emds, sel, strict=True)):
        imfs.append(emd(s)[0])  # (B, n_k, K_k, L_k): the post's example input
        key = (int(s.shape[1]), int(s.shape[2]), emd.n_imfs, emd.n_sifts)
        if key not in bodies:
            bodies[key] = portable_body(emd.n_imfs, emd.n_sifts, *key[:2])
        emd_nodes.append(custom_node("EMD", [ins[k]], [outs[k], f"emd{k}/residue",
                                                       f"emd{k}/n_valid"], f"emd{k}",
                                     n_imfs=emd.n_imfs, n_sifts=emd.n_sifts))
        c_k, t_k = key[:2]  # the node's output shapes (inference through the pick loses them)
        f32, i64 = onnx.TensorProto.FLOAT, onnx.TensorProto.INT64
        shapes += [onnx.helper.make_tensor_value_info(outs[k], f32, [BATCH, c_k, emd.n_imfs, t_k]),
                   onnx.helper.make_tensor_value_info(f"emd{k}/residue", f32, [BATCH, c_k, t_k]),
                   onnx.helper.make_tensor_value_info(f"emd{k}/n_valid", i64, [BATCH, c_k])]
    graphs.append(onnx.helper.make_graph(emd_nodes, "emd", [], []))
    post = trace(_Post(model), [z, *imfs, h, c], ["z", *outs, "h", "c"], OUTPUTS,
                 {"z": batch, **dict.fromkeys(outs, batch), "probs": batch, **state})
    graphs.append(renamed(post, "post/", {n: n for n in ["z", *outs, "h", "c", *OUTPUTS]}))
    functions = [function_of("EMD", [(list(k), g) for k, g in bodies.items()])]
    out = join(graphs, value_info(pre, ["x"]) + value_info(post, ["h", "c"]),
               value_info(post, OUTPUTS), OPSET, "tactile", functions)
    out.graph.value_info.extend(shapes)
    return out
