"""The model object: loads an exported ``.onnx``, checks its contract, classifies windows.

Stateless: the LSTM state lives in each :class:`~tactile.runtime.stream.Stream`, so one
``Model`` serves any number of pens. Needs numpy and onnxruntime only.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import os
from pathlib import Path

import numpy as np
import onnxruntime as ort

from tactile import checksum
from tactile.contract import BATCH, ModelContract, model_file
from tactile.errors import ConfigError, ModelContractError
from tactile.postprocess.smoothing import check_classes, settings_from_metadata
from tactile.runtime import kernels


def session_options(threads: int = 1) -> ort.SessionOptions:
    """onnxruntime settings for a small board: few threads, sequential, no busy-waiting, no
    memory arena.

    Spinning threads burn a core while waiting for work; on a loaded board they were reported to
    push the p99 latency of a 50-sample window from ~0.25 ms to ~8 ms, so they are off. The EMD
    graph allocates hundreds of small tensors a sift: without onnxruntime's CPU arena (plain
    allocations instead) a window of the runtime's model took about 9% less CPU time, and
    the EMD alone 4-7% less at batch 1 (onnxruntime 1.32; ``docs/runtime.md``).
    """
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.enable_cpu_mem_arena = False
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    so.log_severity_level = 3
    return so


# onnxruntime's Python wrapper retries a load that failed with its fallback providers (the
# same CPU provider here) after printing an "EP Error" banner to stdout, which is tactile-run's
# label stream. Versions whose InferenceSession takes enable_fallback are told not to; older
# ones (1.19) print it into a buffer instead, which swaps sys.stdout for the process while the
# session loads.
_NO_FALLBACK = "enable_fallback" in inspect.signature(
    ort.capi.onnxruntime_inference_collection.Session.__init__).parameters


def _session(path: os.PathLike, so: ort.SessionOptions) -> ort.InferenceSession:
    """The CPU session of ``path``, nothing printed on stdout whatever the file holds."""
    if _NO_FALLBACK:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"],
                                    enable_fallback=0)
    with contextlib.redirect_stdout(io.StringIO()):
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def _bytes(path: os.PathLike) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as e:  # gone or unreadable since onnxruntime read it
        raise ModelContractError(f"cannot read it again to check its sha256 ({e.strerror})"
                                 ) from None


class Model:
    """An exported texture model.

    Args:
        path: the ``.onnx`` file written by ``tactile-export``.
        threads: onnxruntime intra-op threads (1 suits a board running one pen).
        options: onnxruntime session options to use instead of ``session_options(threads)``
            (start from :func:`session_options` and change what you need, e.g. allow spinning
            or parallel execution); then ``threads`` is not used and must be left at 1.
            The kernel library is registered in them when the file has custom nodes.

    ``native`` is True when the file's ``ai.tactile`` nodes (EMD, sparse codes) run the C
    kernels, False when they run the file's portable graphs (:mod:`tactile.runtime.kernels`).

    Raises :class:`ModelContractError` (a one-line message naming the problem) if the file is
    missing, not ONNX, not made by the exporter, its graph does not match its metadata, or
    running it on a zero window (batch 1, the runtime's) gives outputs of other shapes or types
    than the contract declares (:meth:`check_outputs`): onnxruntime does not enforce a graph's
    declared output shapes, so a file can declare 5 classes and return 7 probabilities.
    :meth:`classify` checks every result the same way. So is a file whose ``postprocess.*``
    keys are incomplete or bad (:func:`~tactile.postprocess.smoothing.settings_from_metadata`).

    Attributes: ``contract`` (:class:`~tactile.contract.ModelContract`), ``metadata`` (all of
    the file's ``metadata_props``, str -> str), ``postprocess`` (the label stream's
    post-processing defaults, a :class:`~tactile.postprocess.smoothing.SmoothingSettings`, or None
    for a file without ``postprocess.*`` keys), ``path``, ``session``.
    """

    def __init__(self, path: str | os.PathLike, threads: int = 1,
                 options: ort.SessionOptions | None = None) -> None:
        if not (isinstance(threads, int) and threads >= 1):
            raise ConfigError(f"threads {threads!r}: must be an integer >= 1")
        if options is not None and not isinstance(options, ort.SessionOptions):
            raise ConfigError("options: an onnxruntime.SessionOptions, not "
                              f"{type(options).__name__}")
        if options is not None and threads != 1:
            raise ConfigError("give threads or options, not both (set the threads in options)")
        path = model_file(path)
        so = options if options is not None else session_options(threads)
        # the ai.tactile nodes run the C kernels where the library is there, else their
        # portable functions (tactile.runtime.kernels)
        self.native = kernels.register(so, path)
        try:
            self.session = _session(path, so)
            # a damaged file may load and still hold names or metadata that are not UTF-8
            meta = self.session.get_modelmeta().custom_metadata_map
            inputs = [(i.name, i.type, i.shape) for i in self.session.get_inputs()]
            outputs = [(o.name, o.type, o.shape) for o in self.session.get_outputs()]
        except Exception as e:  # noqa: BLE001  (onnxruntime raises its own untyped errors)
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ModelContractError(f"{path}: not a loadable ONNX model ({first})") from None
        try:  # first: a damaged file is named as one, whatever else its damage breaks
            checksum.verify(_bytes(path) if checksum.KEY in meta else b"", meta)
            self.contract = ModelContract.from_metadata(meta)
            self.contract.check_signature(inputs, outputs)
            postprocess = settings_from_metadata(meta)
            if postprocess is not None:  # tactile-run would refuse it at its first window
                try:
                    check_classes(self.contract.classes)
                except ConfigError as e:
                    raise ModelContractError(f"{e} (the file's postprocess.* defaults turn "
                                             "the post-processing on)") from None
        except ModelContractError as e:
            raise ModelContractError(f"{path}: {e}") from None
        self.metadata: dict[str, str] = dict(meta)
        # the label stream's post-processing defaults the file carries (``postprocess.*``,
        # calibrated at export), or None: an older file, run without post-processing
        self.postprocess = postprocess
        self.path = path
        self.probe(1)  # the runtime's batch size, first: a session keeps its first size fast

    def probe(self, batch: int) -> None:
        """Run ``batch`` zero windows from a zero state and check the outputs' shapes and types
        (:meth:`check_outputs`); :class:`ModelContractError` if the run fails or they differ."""
        c = self.contract
        x = np.zeros((batch, c.window, len(c.channels)), np.float32)
        h, cc = self.zero_state(batch)
        try:
            outs = self.session.run(None, {"x": x, "h": h, "c": cc})
        except Exception as e:  # noqa: BLE001  (onnxruntime's untyped errors)
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ModelContractError(f"{self.path}: fails on a zero window at batch {batch} "
                                     f"({first})") from None
        self.check_outputs(outs, batch)
        probs = outs[0]
        if not (np.isfinite(probs).all() and (probs >= -1e-6).all()
                and np.allclose(probs.sum(axis=1), 1.0, atol=1e-3)):
            raise ModelContractError(
                f"{self.path}: output 'probs' on a zero window is {np.round(probs[0], 6).tolist()}"
                f": not probabilities (finite, >= 0, summing to 1), as the contract declares")

    def check_outputs(self, outs: list, batch: int) -> None:
        """Raise :class:`ModelContractError` naming the first output whose shape or dtype is
        not what the contract declares for ``batch`` windows: ``probs`` (batch, classes),
        ``h_out`` and ``c_out`` (layers, batch, hidden), all float32."""
        want = {o.name: tuple(batch if d == BATCH else d for d in o.dims)
                for o in self.contract.outputs}
        if len(outs) != len(want):
            raise ModelContractError(f"{self.path}: the graph returns {len(outs)} outputs, "
                                     f"expected {len(want)} ({', '.join(want)})")
        for (name, shape), out in zip(want.items(), outs):
            got = tuple(np.shape(out))
            if got != shape:
                what = (f"width {got[-1]}, the contract declares {shape[-1]}"
                        if len(got) == len(shape) and got[:-1] == shape[:-1]
                        else f"shape {got}, the contract declares {shape}")
                raise ModelContractError(f"{self.path}: output {name!r} has {what} (batch "
                                         f"{batch})")
            if getattr(out, "dtype", None) != np.float32:
                raise ModelContractError(f"{self.path}: output {name!r} is "
                                         f"{getattr(out, 'dtype', type(out).__name__)}, "
                                         "the contract declares float32")

    @property
    def state_shape(self) -> tuple[int, int]:
        return self.contract.state_layers, self.contract.state_hidden

    def classify(
        self, x: np.ndarray, h: np.ndarray, c: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x (B, window, channels) float32 in units; h, c (layers, B, hidden) float32.

        Returns probabilities (B, classes) and the new h, c; :class:`ModelContractError` when
        the graph returns other shapes (:meth:`check_outputs`).
        """
        outs = self.session.run(
            None, {"x": np.ascontiguousarray(x, np.float32), "h": h, "c": c}
        )
        self.check_outputs(outs, len(x))
        probs, h_out, c_out = outs
        return probs, h_out, c_out

    def zero_state(self, batch: int = 1) -> tuple[np.ndarray, np.ndarray]:
        layers, hidden = self.state_shape
        z = np.zeros((layers, batch, hidden), np.float32)
        return z, z.copy()
