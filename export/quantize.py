"""int8: onnxruntime dynamic quantisation of a float32 export, and batch-1 latency."""

from __future__ import annotations

import logging
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx

from tactile.contract import CUSTOM_DOMAIN
from tactile.export.compose import toposorted
from tactile.export.session import session

# the learned weights; not the spectral front's Conv, whose fixed DFT basis in int8 moves the
# log power of the weak bins by whole units (labels of 12% of windows changed, 53% with EMD)
QUANTIZED_OPS = ("LSTM", "MatMul", "Gemm")
# nor the blended regression's products, for the same reason: its DFT basis and band sums
# feed logs (int8 there: 2 of 3 labels changed on a model that weights the regression fully);
# a granular model computes the regression's window features in its preprocessing
FLOAT_SCOPES = ("/regression/", "/window_features/")


def quantize_int8(model: onnx.ModelProto) -> onnx.ModelProto:
    """Dynamic int8 quantisation (weights int8, activations quantised at run time).

    ``quant_pre_process`` runs first (shape inference and graph clean-up that the quantiser
    relies on); metadata is not carried over: the caller writes the contract afterwards. A
    graph with ``ai.tactile`` nodes skips the pre-process's onnxruntime optimisation, which
    would inline their fallback functions: the int8 file keeps the custom nodes (the kernel
    path) and their functions (the portable one).
    """
    from onnxruntime.quantization import QuantType, quantize_dynamic
    from onnxruntime.quantization.shape_inference import quant_pre_process

    logging.getLogger("root").setLevel(logging.ERROR)  # the quantiser's per-node chatter
    with tempfile.TemporaryDirectory() as tmp:
        src, pre, out = (Path(tmp) / n for n in ("f32.onnx", "pre.onnx", "int8.onnx"))
        onnx.save(model, src)
        custom = any(n.domain == CUSTOM_DOMAIN for n in model.graph.node)
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True,
                          skip_optimization=custom)
        # (the pre-process fuses a MatMul + Add into a Gemm, which the quantiser splits again
        # into a MatMul named after it: both names are excluded)
        kept = [name for n in onnx.load(pre).graph.node
                if any(scope in n.name for scope in FLOAT_SCOPES)
                for name in (n.name, f"{n.name}_MatMul")]
        quantize_dynamic(str(pre), str(out), weight_type=QuantType.QInt8,
                         op_types_to_quantize=list(QUANTIZED_OPS), nodes_to_exclude=kept)
        # the optimiser orders nodes by their explicit inputs only; a Loop or If body may read
        # a value of the main graph (the EMD graphs' constants) that it then puts later
        return toposorted(onnx.load(out))


def latency_ms(model: bytes | str, window: int, channels: int, state: tuple[int, int],
               runs: int = 200, seed: int = 0, native: bool = False) -> dict[str, float]:
    """Batch-1 latency of one window on one thread: p50 and p99 in milliseconds; with
    ``native`` the file's custom nodes run on the kernel library."""
    sess = session(model, native=native)
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((1, window, channels)).astype(np.float32)
    h = np.zeros((state[0], 1, state[1]), np.float32)
    feed = {"x": x, "h": h, "c": h}
    for _ in range(10):
        sess.run(None, feed)
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        sess.run(None, feed)
        times.append((time.perf_counter() - t) * 1e3)
    return {"p50_ms": round(float(np.percentile(times, 50)), 4),
            "p99_ms": round(float(np.percentile(times, 99)), 4)}
