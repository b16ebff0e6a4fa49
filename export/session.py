"""The onnxruntime session every export check runs a graph in (CPU, sequential, no spinning).

By default the portable path: a file's ``ai.tactile`` nodes run their model-local functions
(the standard-op graphs). ``native=True`` registers the kernel library, when it is built and
enabled, so that they run the C kernels (:func:`native_available`)."""

from __future__ import annotations

import onnxruntime as ort


def native_available() -> bool:
    """Whether the kernel library is built, not turned off (``TACTILE_NATIVE``) and loads."""
    from tactile import native

    return native.available()


def session(model: bytes | str, threads: int = 1, native: bool = False) -> ort.InferenceSession:
    """A CPU session: ``threads`` intra-op threads, sequential, no busy-wait spinning; with
    ``native`` the kernel library registered (an error if it is not there)."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    if native:
        from tactile import native as kernels

        path = kernels.library_path()
        if path is None:
            raise kernels.NativeError("the native kernels are not built or are disabled")
        so.register_custom_ops_library(str(path))
    return ort.InferenceSession(model, so, providers=["CPUExecutionProvider"])


__all__ = ["native_available", "session"]
