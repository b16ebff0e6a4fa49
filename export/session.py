"""The onnxruntime session every export check runs a graph in (CPU, sequential, no spinning)."""

from __future__ import annotations

import onnxruntime as ort


def session(model: bytes | str, threads: int = 1) -> ort.InferenceSession:
    """A CPU session: ``threads`` intra-op threads, sequential, no busy-wait spinning."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    return ort.InferenceSession(model, so, providers=["CPUExecutionProvider"])


__all__ = ["session"]
