"""The deployable graph: raw window + state in, class probabilities + new state out.

Exporter path (pinned): ``torch.onnx.export(..., dynamo=False)`` (the TorchScript exporter) at
opset :data:`tactile.contract.OPSET` (18), with an example batch of 3 and ``batch`` declared
dynamic. It captures ``nn.LSTM`` as ONNX ``LSTM`` nodes with a symbolic batch, and it is the path
the EMD graph is built with, so both halves share one exporter.

Without EMD features the whole :class:`TextureModel` is one export. With them the graph is
composed of three parts, because the EMD is assembled by hand with ``Loop`` nodes
(:func:`tactile.training.emd.onnx_export.build_emd_model`) rather than traced::

    x (B, T, C) -> [pre: normalise, centre, pick EMD channels] -> z (B, T, C), sel (B, Ce, T)
    sel -> [EMD Loop graph, float32] -> imfs (B, Ce, K, T)
    z, imfs, h, c -> [post: concatenate features, head, softmax] -> probs (B, classes), h, c

``pre`` and ``post`` reuse the trained model's own buffers and head; the export-time parity check
compares the composed graph with ``TextureModel.forward`` itself, so a drift between this split
and the training code fails the export.
"""

from __future__ import annotations

import onnx
import torch
from torch import Tensor, nn

import tactile
from tactile.contract import BATCH, INPUTS, OPSET, OUTPUTS
from tactile.export.compose import join, renamed, value_info
from tactile.training.emd.onnx_export import build_emd_model, export_traced
from tactile.training.model import Preprocess, TextureModel

EXAMPLE_BATCH = 3
"""Example batch of the traced export: > 1, so that the tracer cannot fix the batch size."""
IR_VERSION = 8
"""ONNX IR version written (onnxruntime >= 1.15 reads it)."""
EXPORTER = f"torch.onnx.export dynamo=False (TorchScript), opset {OPSET}"

_STATE_AXES = {1: BATCH}


class _Pre(nn.Module):
    """x (B, T, C) in units -> z (B, T, C) normalised and centred, sel (B, Ce, T) for the EMD.

    The same ops, in the same order, as the first half of :meth:`Preprocess.forward`.
    """

    def __init__(self, pre: Preprocess) -> None:
        super().__init__()
        self.pre = pre

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        p = self.pre
        z = (x - p.mean) / p.std  # (B, T, C)
        z = z - z.mean(dim=1, keepdim=True) * p.center_mask
        sel = torch.index_select(z, 2, p.emd_index).transpose(1, 2)  # (B, Ce, T)
        return z, sel


class _Post(nn.Module):
    """z (B, T, C), imfs (B, Ce, K, T), h, c (L, B, H) -> probs (B, classes), h, c."""

    def __init__(self, model: TextureModel) -> None:
        super().__init__()
        self.head = model.head

    def forward(self, z: Tensor, imfs: Tensor, h: Tensor, c: Tensor):
        feats = imfs.flatten(1, 2).transpose(1, 2)  # (B, T, Ce*K)
        f = torch.cat([z, feats.to(z.dtype)], dim=2)  # (B, T, C + Ce*K)
        logits, h, c = self.head(f, h, c)
        return torch.softmax(logits, dim=1), h, c


def split_forward(model: TextureModel, x: Tensor, h: Tensor, c: Tensor):
    """The composed graph's computation in eager torch (pre, torch EMD, post), for tests."""
    z, sel = _Pre(model.pre)(x)
    imfs, _, _ = model.pre.emd(sel)
    return _Post(model)(z, imfs, h, c)


trace = export_traced  # the pinned exporter path, shared with the EMD graph


def build_graph(model: TextureModel) -> onnx.ModelProto:
    """The float32 graph of ``model`` (no metadata yet), checked by ``onnx.checker``.

    Inputs ``x`` (batch, window, channels), ``h``, ``c`` (layers, batch, hidden); outputs
    ``probs`` (batch, classes), ``h_out``, ``c_out`` (layers, batch, hidden).
    """
    model = model.eval().float()
    cfg = model.cfg
    b, t, ch = EXAMPLE_BATCH, cfg.window, model.pre.n_channels
    x = torch.randn(b, t, ch) * model.pre.std + model.pre.mean  # (B, T, C) in units
    h, c = model.zero_state(b)
    state = {"h": _STATE_AXES, "c": _STATE_AXES, "h_out": _STATE_AXES, "c_out": _STATE_AXES}
    with torch.no_grad():
        if model.pre.emd is None:
            out = trace(model, [x, h, c], INPUTS, OUTPUTS,
                        {"x": {0: BATCH}, "probs": {0: BATCH}, **state})
        else:
            out = _compose(model, x, h, c, state)
    out.ir_version = IR_VERSION
    out.producer_name = "tactile.export"
    out.producer_version = tactile.__version__
    onnx.checker.check_model(out, full_check=True)
    return out


def _compose(model: TextureModel, x: Tensor, h: Tensor, c: Tensor, state: dict) -> onnx.ModelProto:
    pre_m = _Pre(model.pre)
    z, sel = pre_m(x)
    emd = model.pre.emd
    imfs, _, _ = emd(sel)
    pre = trace(pre_m, [x], ["x"], ["z", "sel"],
                {"x": {0: BATCH}, "z": {0: BATCH}, "sel": {0: BATCH}})
    mid = build_emd_model(emd.n_imfs, emd.n_sifts, int(sel.shape[1]), int(sel.shape[2]),
                          torch.float32)
    post = trace(_Post(model), [z, imfs, h, c], ["z", "imfs", "h", "c"], OUTPUTS,
                 {"z": {0: BATCH}, "imfs": {0: BATCH}, "probs": {0: BATCH}, **state})
    emd_in, emd_out = mid.graph.input[0].name, mid.graph.output[0].name  # x_in, imfs
    graphs = [
        renamed(pre, "pre/", {"x": "x", "z": "z", "sel": "emd_in"}),
        renamed(mid, "emd/", {emd_in: "emd_in", emd_out: "imfs"}),
        renamed(post, "post/", {n: n for n in ["z", "imfs", "h", "c", *OUTPUTS]}),
    ]
    return join(graphs, value_info(pre, ["x"]) + value_info(post, ["h", "c"]),
                value_info(post, OUTPUTS), OPSET, "tactile")
