"""The contract's names and numbers, one definition each: the metadata keys (:data:`KEYS`),
the format, preprocessing, opset and IR versions, the model families and the limits. The
contract itself (:mod:`tactile.contract`) re-exports every one of them."""

from __future__ import annotations

FORMAT = "tactile-onnx"
"""Value of the ``tactile.format`` key: marks a file made by ``tactile-export``."""
FORMAT_VERSION = 2
"""Newest version of this contract this reader understands; it refuses newer files. A file is
written with the lowest version that holds it: 1 for the pen's models (``lstm``, ``linear``
without modalities: readable by every reader), 2 for the granular models (the ``signals`` and
``modalities`` keys, ``model`` ``sf_rnn``, ``f_rnn``, ``sparse_linear``), which a version-1
reader refuses in one line (``tactile.format_version`` is 2; it understands 1..1)."""
PREPROCESSING_VERSION = 2
"""Newest in-graph preprocessing this reader understands: 1 normalise, centre, EMD features,
concatenate (the pen's models); 2 per-modality EMD, data images and sparse codes (described by
the ``modalities`` key)."""
OPSET = 18
"""ONNX opset (default domain) the exporter writes (ScatterElements with a reduction, which the
EMD graph uses, needs >= 16)."""
IR_VERSION = 8
"""ONNX IR version the exporter writes (onnxruntime >= 1.15 reads it)."""
CUSTOM_DOMAIN = "ai.tactile"
"""The toolkit's op domain (version 1): ``EMD`` and ``SparseCode`` nodes, each with a model-local
function of the same name as its portable fallback (``tactile.export.custom_ops``)."""

INPUTS = ("x", "h", "c")
OUTPUTS = ("probs", "h_out", "c_out")
BATCH = "batch"
"""Name of the dynamic batch axis in the graph."""
FLOAT = "tensor(float)"
"""Element type of every input and output, as onnxruntime spells it."""

STATE_MODES = ("window", "carry")
MODELS = ("lstm", "linear", "sf_rnn", "f_rnn", "sparse_linear")
RECURRENT = ("lstm", "sf_rnn", "f_rnn")
"""Models with an LSTM state (may carry it); the others pass a (1, batch, 1) state through."""
MODALITY_MODELS = ("sf_rnn", "f_rnn", "sparse_linear")
"""Models that need the ``modalities`` key (``linear`` may have it; ``lstm`` may not)."""
CODED_MODELS = ("sf_rnn", "sparse_linear")
"""Models whose features are sparse codes (each modality has a dictionary: atoms, nonzero)."""
MAX_RATE_HZ = 1e6
"""Highest sample rate a device header or a model file may state (Hz)."""
MAX_IMFS = 16
"""Most IMFs of one EMD (:class:`tactile.training.emd.EMDConfig`'s limit, PyEMD ``max_imf``)."""
MAX_SIFTS = 1000
"""Most sifts per IMF of one EMD (:class:`tactile.training.emd.EMDConfig`'s limit, PyEMD
``FIXE``)."""
QUANTIZATIONS = ("none", "int8-dynamic")

# One source of truth for the metadata keys: name -> (required, meaning).
KEYS: dict[str, tuple[bool, str]] = {
    "tactile.format": (True, f'"{FORMAT}": the file was made by tactile-export'),
    "tactile.format_version": (True, f"contract version (integer, this reader: {FORMAT_VERSION})"),
    "classes": (True, "JSON list of class names, in the order of the probabilities"),
    "channels": (True, "JSON list of input channel names, in the order of x's last axis"),
    "units": (True, "JSON list of each channel's unit (x is in these units, as the device sends)"),
    "sample_rate_hz": (True, "sample rate the model was trained at (Hz, number)"),
    "window": (True, "samples per window (integer): x's time axis"),
    "hop": (True, "samples between window starts (integer); carry mode needs hop == window"),
    "state_mode": (True, '"window": zero state per window; "carry": feed h_out, c_out back'),
    "model": (True, '"lstm", "linear", "sf_rnn", "f_rnn" or "sparse_linear" (linear and '
                    'sparse_linear pass the state through)'),
    "state_layers": (True, "state tensors' first axis (integer)"),
    "state_hidden": (True, "state tensors' last axis (integer)"),
    "preprocessing": (True, "JSON object: mean, std (per channel), center (channel names), "
                            "emd (null or {channels, imfs, sifts}), as computed in the graph; "
                            "with modalities also sifts (the modalities' EMD sifts); with "
                            "high-rate signals in an lstm's spectral front also high_rate "
                            "(per signal: signal, rate_hz, frame and hop in its samples, "
                            "bands_hz [[lo, hi], ...]: its log band powers per frame)"),
    "preprocessing_version": (True, f"version of the preprocessing (integer, this reader: "
                                    f"{PREPROCESSING_VERSION})"),
    "package_version": (True, "tactile version that exported the file"),
    "training_metrics": (True, "JSON object: the run's test figures (accuracy, windows, ...)"),
    "parity": (True, "JSON object: ONNX vs PyTorch figures measured at export (passed, ...)"),
    "quantization": (True, '"none" (float32) or "int8-dynamic"'),
    "signals": (False, "JSON list of high-rate signals {name, channels (sub-samples of a "
                       "frame, in time order), rate_hz}: the graph treats each as one signal "
                       "at rate_hz (a granular model's modalities, an lstm's spectral "
                       "front: preprocessing.high_rate); absent: none (format version 2)"),
    "modalities": (False, "JSON list of modalities {name, channels (names, in the order the "
                          "graph takes them), signal, rate_hz, imfs, steps, atoms, nonzero}; "
                          "absent: none (format version 2)"),
    "exporter": (False, "how the graph was made: torch version, exporter path, opset"),
    "custom_ops": (False, f"JSON object: the graph's {CUSTOM_DOMAIN} nodes {{domain, version, "
                          "nodes: [{op, name, attributes}], fallback}: each runs the native "
                          "kernel where onnxruntime has the library registered, else the "
                          "model-local function of its name (the portable graph); absent: none"),
    "sha256": (False, "SHA-256 (64 lower-case hex digits) of the file's bytes with this value "
                      "written as 64 '0' characters: a file whose bytes give another is refused "
                      "as damaged (tactile.checksum); absent: not checked"),
    "training_config": (False, "JSON object: the run's resolved training config"),
    "source_run": (False, "name of the run folder the model came from"),
    # the label stream's post-processing defaults (tactile.postprocess.smoothing reads them):
    # all four or none; a file without them runs raw
    "postprocess.version": (False, "version of the postprocess.* keys' meaning (this reader: "
                                   "1); with smooth, p_min and hold"),
    "postprocess.smooth": (False, "the averaging of the class probabilities: ma:N (the last N "
                                  "windows) or ema:TAU (an exponential average, TAU in s)"),
    "postprocess.p_min": (False, "a stable label's least averaged probability (0..1)"),
    "postprocess.hold": (False, "windows a class must lead before its label is stable (>= 1)"),
    "postprocess.calibration": (False, "JSON object: how the defaults were chosen and the "
                                       "figures they gave on the validation streams"),
}
POSTPROCESS_PREFIX = "postprocess."
"""Prefix of the label stream's post-processing keys in :data:`KEYS`."""
REQUIRED = tuple(k for k, (req, _) in KEYS.items() if req)
OPTIONAL = tuple(k for k, (req, _) in KEYS.items() if not req)
PARSED_OPTIONAL = ("signals", "modalities")
"""Optional keys parsed into :class:`ModelContract` fields (the others are kept as text)."""


__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "PREPROCESSING_VERSION",
    "OPSET",
    "IR_VERSION",
    "CUSTOM_DOMAIN",
    "INPUTS",
    "OUTPUTS",
    "BATCH",
    "FLOAT",
    "STATE_MODES",
    "MODELS",
    "RECURRENT",
    "MODALITY_MODELS",
    "CODED_MODELS",
    "MAX_RATE_HZ",
    "MAX_IMFS",
    "MAX_SIFTS",
    "QUANTIZATIONS",
    "KEYS",
    "POSTPROCESS_PREFIX",
    "REQUIRED",
    "OPTIONAL",
    "PARSED_OPTIONAL",
]
