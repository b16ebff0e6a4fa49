"""The ONNX model contract (export -> runtime): names, shapes and metadata keys, defined once.

The exporter writes it and the runtime reads it; both import this module, which needs nothing
beyond the standard library (no numpy, no onnx, no torch), so the runtime can use it on a board.

The graph::

    inputs   x      float32 (batch, window, channels)   samples in the device's units
             h      float32 (layers, batch, hidden)     state in
             c      float32 (layers, batch, hidden)
    outputs  probs  float32 (batch, classes)            softmax probabilities, classes order
             h_out  float32 (layers, batch, hidden)     state out
             c_out  float32 (layers, batch, hidden)

``batch`` is the only dynamic axis. A head without state (``model = linear``) still has the
state inputs and outputs, of shape (1, batch, 1), passed through unchanged.

The metadata (``metadata_props``) holds strings; lists and dicts are JSON. :data:`KEYS` lists
every key with its meaning; :meth:`ModelContract.from_metadata` validates them all and raises
:class:`ModelContractError` naming the first bad or missing key.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tactile.errors import ModelContractError

FORMAT = "tactile-onnx"
"""Value of the ``tactile.format`` key: marks a file made by ``tactile-export``."""
FORMAT_VERSION = 1
"""Version of this contract; a reader refuses files of a newer version."""
PREPROCESSING_VERSION = 1
"""Version of the in-graph preprocessing (normalise, centre, EMD features, concatenate)."""
OPSET = 18
"""ONNX opset (default domain) the exporter writes."""

INPUTS = ("x", "h", "c")
OUTPUTS = ("probs", "h_out", "c_out")
BATCH = "batch"
"""Name of the dynamic batch axis in the graph."""
FLOAT = "tensor(float)"
"""Element type of every input and output, as onnxruntime spells it."""

STATE_MODES = ("window", "carry")
MODELS = ("lstm", "linear")
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
    "model": (True, '"lstm" or "linear" (a linear head passes the state through)'),
    "state_layers": (True, "state tensors' first axis (integer)"),
    "state_hidden": (True, "state tensors' last axis (integer)"),
    "preprocessing": (True, "JSON object: mean, std (per channel), center (channel names), "
                            "emd (null or {channels, imfs, sifts}), as computed in the graph"),
    "preprocessing_version": (True, f"version of the preprocessing (integer, this reader: "
                                    f"{PREPROCESSING_VERSION})"),
    "package_version": (True, "tactile version that exported the file"),
    "training_metrics": (True, "JSON object: the run's test figures (accuracy, windows, ...)"),
    "parity": (True, "JSON object: ONNX vs PyTorch figures measured at export (passed, ...)"),
    "quantization": (True, '"none" (float32) or "int8-dynamic"'),
    "exporter": (False, "how the graph was made: torch version, exporter path, opset"),
    "training_config": (False, "JSON object: the run's resolved training config"),
    "source_run": (False, "name of the run folder the model came from"),
}
REQUIRED = tuple(k for k, (req, _) in KEYS.items() if req)
OPTIONAL = tuple(k for k, (req, _) in KEYS.items() if not req)


@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output: ``dims`` holds ints, or :data:`BATCH` for the dynamic axis."""

    name: str
    dims: tuple[int | str, ...]
    elem_type: str = FLOAT


@dataclass(frozen=True)
class ModelContract:
    """Everything the runtime needs to honour a model, parsed from its metadata."""

    classes: tuple[str, ...]
    channels: tuple[str, ...]
    units: tuple[str, ...]
    sample_rate_hz: float
    window: int
    hop: int
    state_mode: str
    model: str
    state_layers: int
    state_hidden: int
    preprocessing: dict[str, Any]
    package_version: str
    training_metrics: dict[str, Any]
    parity: dict[str, Any]
    quantization: str = "none"
    preprocessing_version: int = PREPROCESSING_VERSION
    format_version: int = FORMAT_VERSION
    extra: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _validate(self)

    # -- metadata ----------------------------------------------------------------------------

    @classmethod
    def from_metadata(cls, meta: Mapping[str, str]) -> ModelContract:
        """Parse and validate ``metadata_props`` (a str -> str mapping)."""
        if "tactile.format" not in meta:
            raise ModelContractError("metadata key 'tactile.format' is missing: not a model "
                                     "made by tactile-export")
        if meta["tactile.format"] != FORMAT:
            raise ModelContractError(
                f"metadata key 'tactile.format' is {meta.get('tactile.format')!r}, expected "
                f"{FORMAT!r}: not a model made by tactile-export"
            )
        missing = [k for k in REQUIRED if k not in meta]
        if missing:
            raise ModelContractError(f"metadata key {missing[0]!r} is missing "
                                     f"({KEYS[missing[0]][1]})")
        version = _int(meta, "tactile.format_version")
        if version > FORMAT_VERSION or version < 1:
            raise ModelContractError(f"metadata key 'tactile.format_version' is {version}; "
                                     f"this reader understands 1..{FORMAT_VERSION}")
        return cls(
            classes=_names(meta, "classes"),
            channels=_names(meta, "channels"),
            units=_strings(meta, "units"),
            sample_rate_hz=_number(meta, "sample_rate_hz"),
            window=_int(meta, "window"),
            hop=_int(meta, "hop"),
            state_mode=_choice(meta, "state_mode", STATE_MODES),
            model=_choice(meta, "model", MODELS),
            state_layers=_int(meta, "state_layers"),
            state_hidden=_int(meta, "state_hidden"),
            preprocessing=_object(meta, "preprocessing"),
            preprocessing_version=_int(meta, "preprocessing_version"),
            package_version=_text(meta, "package_version"),
            training_metrics=_object(meta, "training_metrics"),
            parity=_object(meta, "parity"),
            quantization=_choice(meta, "quantization", QUANTIZATIONS),
            format_version=version,
            extra={k: v for k, v in meta.items() if k in OPTIONAL},
        )

    def to_metadata(self) -> dict[str, str]:
        """The ``metadata_props`` strings; ``from_metadata(to_metadata())`` gives ``self``."""
        meta = {
            "tactile.format": FORMAT,
            "tactile.format_version": str(self.format_version),
            "classes": json.dumps(list(self.classes)),
            "channels": json.dumps(list(self.channels)),
            "units": json.dumps(list(self.units)),
            "sample_rate_hz": repr(float(self.sample_rate_hz)),
            "window": str(self.window),
            "hop": str(self.hop),
            "state_mode": self.state_mode,
            "model": self.model,
            "state_layers": str(self.state_layers),
            "state_hidden": str(self.state_hidden),
            "preprocessing": json.dumps(self.preprocessing, sort_keys=True),
            "preprocessing_version": str(self.preprocessing_version),
            "package_version": self.package_version,
            "training_metrics": json.dumps(self.training_metrics, sort_keys=True),
            "parity": json.dumps(self.parity, sort_keys=True),
            "quantization": self.quantization,
        }
        meta.update(self.extra)
        return meta

    # -- graph signature ---------------------------------------------------------------------

    @property
    def inputs(self) -> tuple[TensorSpec, ...]:
        """x (batch, window, channels), h and c (layers, batch, hidden)."""
        state = (self.state_layers, BATCH, self.state_hidden)
        return (TensorSpec("x", (BATCH, self.window, len(self.channels))),
                TensorSpec("h", state), TensorSpec("c", state))

    @property
    def outputs(self) -> tuple[TensorSpec, ...]:
        """probs (batch, classes), h_out and c_out (layers, batch, hidden)."""
        state = (self.state_layers, BATCH, self.state_hidden)
        return (TensorSpec("probs", (BATCH, len(self.classes))),
                TensorSpec("h_out", state), TensorSpec("c_out", state))

    def check_signature(self, inputs: Iterable[Sequence], outputs: Iterable[Sequence]) -> None:
        """Check a graph's (name, elem_type, shape) triples against the contract.

        ``elem_type`` is onnxruntime's spelling (``tensor(float)``); ``shape`` holds ints for
        fixed axes and a string or None for symbolic ones (as ``session.get_inputs()`` gives).
        Raises :class:`ModelContractError` naming the first mismatch.
        """
        for kind, want, got in (("input", self.inputs, list(inputs)),
                                ("output", self.outputs, list(outputs))):
            names = [g[0] for g in got]
            if names != [w.name for w in want]:
                raise ModelContractError(f"graph {kind}s are {names}, expected "
                                         f"{[w.name for w in want]}")
            for spec, (name, elem, shape) in zip(want, got):
                if elem != spec.elem_type:
                    raise ModelContractError(f"{kind} {name!r} has type {elem}, expected "
                                             f"{spec.elem_type}")
                _check_dims(kind, name, list(shape), spec.dims)


def _check_dims(kind: str, name: str, shape: list, dims: tuple[int | str, ...]) -> None:
    def show(d: tuple | list) -> str:
        return "(" + ", ".join("?" if v is None else str(v) for v in d) + ")"

    if len(shape) != len(dims):
        raise ModelContractError(f"{kind} {name!r} has rank {len(shape)} {show(shape)}, "
                                 f"expected {show(dims)}")
    for axis, (got, want) in enumerate(zip(shape, dims)):
        if want == BATCH:
            if isinstance(got, int):
                raise ModelContractError(
                    f"{kind} {name!r} axis {axis} (batch) is fixed to {got}: it must be dynamic "
                    f"(shape {show(shape)}, expected {show(dims)})")
        elif got != want:
            raise ModelContractError(f"{kind} {name!r} has shape {show(shape)}, expected "
                                     f"{show(dims)}")


# -- validation ---------------------------------------------------------------------------------


def _validate(c: ModelContract) -> None:
    def bad(key: str, msg: str) -> None:
        raise ModelContractError(f"metadata key {key!r}: {msg}")

    if len(c.classes) < 2:
        bad("classes", f"needs at least 2 classes, got {list(c.classes)}")
    if not c.channels:
        bad("channels", "needs at least 1 channel")
    if len(c.units) != len(c.channels):
        bad("units", f"{len(c.units)} units for {len(c.channels)} channels")
    if not (math.isfinite(c.sample_rate_hz) and c.sample_rate_hz > 0):
        bad("sample_rate_hz", f"must be a finite number > 0, got {c.sample_rate_hz}")
    for key in ("window", "hop", "state_layers", "state_hidden"):
        if getattr(c, key) < 1:
            bad(key, f"must be >= 1, got {getattr(c, key)}")
    if c.state_mode not in STATE_MODES:
        bad("state_mode", f"{c.state_mode!r} is not one of {', '.join(STATE_MODES)}")
    if c.model not in MODELS:
        bad("model", f"{c.model!r} is not one of {', '.join(MODELS)}")
    if c.quantization not in QUANTIZATIONS:
        bad("quantization", f"{c.quantization!r} is not one of {', '.join(QUANTIZATIONS)}")
    if c.state_mode == "carry" and c.hop != c.window:
        bad("hop", f"carry mode needs hop == window (hop {c.hop}, window {c.window})")
    if c.state_mode == "carry" and c.model != "lstm":
        bad("state_mode", "carry mode needs model 'lstm'")
    if c.model == "linear" and (c.state_layers, c.state_hidden) != (1, 1):
        bad("state_layers", "a linear head's state is (1, batch, 1)")
    if c.preprocessing_version != PREPROCESSING_VERSION:
        bad("preprocessing_version", f"{c.preprocessing_version}; this reader understands "
                                     f"{PREPROCESSING_VERSION}")
    _validate_preprocessing(c.preprocessing, c.channels, bad)
    if not isinstance(c.parity.get("passed"), bool):
        bad("parity", "needs a boolean 'passed'")
    if not c.package_version:
        bad("package_version", "must not be empty")


def _validate_preprocessing(p: dict, channels: tuple[str, ...], bad) -> None:
    key = "preprocessing"
    for name in ("mean", "std"):
        v = p.get(name)
        if not (isinstance(v, list) and len(v) == len(channels) and all(_isnum(x) for x in v)):
            bad(key, f"{name!r} must be a list of {len(channels)} numbers")
    if any(s <= 0 for s in p["std"]):
        bad(key, "'std' must be > 0")
    center = p.get("center")
    if not (isinstance(center, list) and all(x in channels for x in center)):
        bad(key, f"'center' must list channel names among {list(channels)}")
    emd = p.get("emd", "absent")
    if emd == "absent":
        bad(key, "'emd' is missing (null when the model has no EMD features)")
    if emd is None:
        return
    if not isinstance(emd, dict):
        bad(key, "'emd' must be null or an object")
    ch = emd.get("channels")
    if not (isinstance(ch, list) and ch and all(x in channels for x in ch)):
        bad(key, f"'emd.channels' must list channel names among {list(channels)}")
    for name in ("imfs", "sifts"):
        v = emd.get(name)
        if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
            bad(key, f"'emd.{name}' must be an integer >= 1")


def _isnum(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _json(meta: Mapping[str, str], key: str) -> Any:
    try:
        return json.loads(meta[key])
    except (TypeError, ValueError) as e:
        raise ModelContractError(f"metadata key {key!r} is not valid JSON ({e})") from None


def _names(meta: Mapping[str, str], key: str) -> tuple[str, ...]:
    v = _strings(meta, key)
    if len(set(v)) != len(v) or not all(v):
        raise ModelContractError(f"metadata key {key!r}: names must be unique and non-empty, "
                                 f"got {list(v)}")
    return v


def _strings(meta: Mapping[str, str], key: str) -> tuple[str, ...]:
    v = _json(meta, key)
    if not (isinstance(v, list) and all(isinstance(x, str) for x in v)):
        raise ModelContractError(f"metadata key {key!r} must be a JSON list of strings, "
                                 f"got {meta[key][:60]!r}")
    return tuple(v)


def _object(meta: Mapping[str, str], key: str) -> dict:
    v = _json(meta, key)
    if not isinstance(v, dict):
        raise ModelContractError(f"metadata key {key!r} must be a JSON object, "
                                 f"got {meta[key][:60]!r}")
    return v


def _int(meta: Mapping[str, str], key: str) -> int:
    try:
        return int(meta[key])
    except ValueError:
        raise ModelContractError(f"metadata key {key!r} must be an integer, "
                                 f"got {meta[key][:60]!r}") from None


def _number(meta: Mapping[str, str], key: str) -> float:
    try:
        return float(meta[key])
    except ValueError:
        raise ModelContractError(f"metadata key {key!r} must be a number, "
                                 f"got {meta[key][:60]!r}") from None


def _text(meta: Mapping[str, str], key: str) -> str:
    return str(meta[key])


def _choice(meta: Mapping[str, str], key: str, allowed: tuple[str, ...]) -> str:
    v = meta[key]
    if v not in allowed:
        raise ModelContractError(f"metadata key {key!r} is {v[:60]!r}, allowed: "
                                 f"{', '.join(allowed)}")
    return v


def model_file(path: str | Path) -> Path:
    """``path`` as a model file to load: :class:`ModelContractError` (exit 3) when it is missing
    or a folder, with the same line in every command that loads a model."""
    path = Path(path)
    if path.is_dir():
        raise ModelContractError(f"{path}: a folder, not a model file (give the .onnx file)")
    if not path.is_file():
        raise ModelContractError(f"{path}: no such model file")
    return path


__all__ = [
    "FORMAT", "FORMAT_VERSION", "PREPROCESSING_VERSION", "OPSET", "INPUTS", "OUTPUTS", "BATCH",
    "FLOAT", "KEYS", "REQUIRED", "OPTIONAL", "STATE_MODES", "MODELS", "QUANTIZATIONS",
    "TensorSpec", "ModelContract", "model_file",
]

