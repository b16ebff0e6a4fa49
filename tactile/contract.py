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

from tactile import metadata_fields as F
from tactile.contract_keys import (  # noqa: F401  (re-exported: the contract's names)
    BATCH,
    CODED_MODELS,
    CUSTOM_DOMAIN,
    FLOAT,
    FORMAT,
    FORMAT_VERSION,
    INPUTS,
    IR_VERSION,
    KEYS,
    MAX_IMFS,
    MAX_RATE_HZ,
    MAX_SIFTS,
    MODALITY_MODELS,
    MODELS,
    OPSET,
    OPTIONAL,
    OUTPUTS,
    PARSED_OPTIONAL,
    POSTPROCESS_PREFIX,
    PREPROCESSING_VERSION,
    QUANTIZATIONS,
    RECURRENT,
    REQUIRED,
    STATE_MODES,
)
from tactile.errors import ModelContractError


@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output: ``dims`` holds ints, or :data:`BATCH` for the dynamic axis."""

    name: str
    dims: tuple[int | str, ...]
    elem_type: str = FLOAT


@dataclass(frozen=True)
class SignalSpec:
    """A high-rate signal: ``channels`` are the consecutive sub-samples of one frame, in time
    order, so the signal runs at ``rate_hz`` = the sample rate x ``len(channels)``."""

    name: str
    channels: tuple[str, ...]
    rate_hz: float

    def to_json(self) -> dict:
        return {"name": self.name, "channels": list(self.channels), "rate_hz": self.rate_hz}


@dataclass(frozen=True)
class ModalitySpec:
    """A modality as the graph computes it.

    ``channels``: x's channel names in the order the graph takes them (a signal's sub-samples
    together, in time order); ``signal``: they are whole high-rate signals (else plain
    channels); ``rate_hz``: the modality's rate; ``imfs``: IMFs of its EMD (0: none);
    ``steps``: image time steps at its rate; ``atoms``, ``nonzero``: its dictionary's size and
    the codes' non-zeros (the number the graph uses; 0 when the model has no codes).
    """

    name: str
    channels: tuple[str, ...]
    signal: bool
    rate_hz: float
    imfs: int
    steps: int
    atoms: int
    nonzero: int

    def to_json(self) -> dict:
        return {"name": self.name, "channels": list(self.channels), "signal": self.signal,
                "rate_hz": self.rate_hz, "imfs": self.imfs, "steps": self.steps,
                "atoms": self.atoms, "nonzero": self.nonzero}


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
    preprocessing_version: int | None = None  # None: the version this content needs
    format_version: int | None = None  # None: the lowest version that holds this content
    extra: dict[str, str] = field(default_factory=dict)
    signals: tuple[SignalSpec, ...] = ()
    modalities: tuple[ModalitySpec, ...] = ()

    def __post_init__(self) -> None:
        if self.preprocessing_version is None:
            object.__setattr__(self, "preprocessing_version", 2 if self.modalities else 1)
        if self.format_version is None:
            object.__setattr__(self, "format_version", self.needed_format_version())
        _validate(self)

    def needed_format_version(self) -> int:
        """The lowest contract version that holds this content: 2 with signals, modalities or a
        granular model, else 1."""
        granular = self.signals or self.modalities or self.model not in ("lstm", "linear")
        return 2 if granular else 1

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
        version = F.integer(meta, "tactile.format_version")
        if version > FORMAT_VERSION or version < 1:
            raise ModelContractError(f"metadata key 'tactile.format_version' is {version}; "
                                     f"this reader understands 1..{FORMAT_VERSION}")
        contract = cls(
            classes=F.names(meta, "classes"),
            channels=F.names(meta, "channels"),
            units=F.strings(meta, "units"),
            sample_rate_hz=F.number(meta, "sample_rate_hz"),
            window=F.integer(meta, "window"),
            hop=F.integer(meta, "hop"),
            state_mode=F.choice(meta, "state_mode", STATE_MODES),
            model=F.choice(meta, "model", MODELS),
            state_layers=F.integer(meta, "state_layers"),
            state_hidden=F.integer(meta, "state_hidden"),
            preprocessing=F.json_object(meta, "preprocessing"),
            preprocessing_version=F.integer(meta, "preprocessing_version"),
            package_version=F.text(meta, "package_version"),
            training_metrics=F.json_object(meta, "training_metrics"),
            parity=F.json_object(meta, "parity"),
            quantization=F.choice(meta, "quantization", QUANTIZATIONS),
            format_version=version,
            extra={k: v for k, v in meta.items() if k in OPTIONAL and k not in PARSED_OPTIONAL},
            signals=_signals(meta),
            modalities=_modalities(meta),
        )
        contract.custom_ops  # noqa: B018  (read once: a bad key is named now, on every path)
        return contract

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
        if self.signals:
            meta["signals"] = json.dumps([s.to_json() for s in self.signals])
        if self.modalities:
            meta["modalities"] = json.dumps([m.to_json() for m in self.modalities])
        meta.update(self.extra)
        return meta

    @property
    def custom_ops(self) -> list[dict[str, Any]]:
        """The ``custom_ops`` key's nodes ({op, name, attributes}), [] without the key."""
        raw = self.extra.get("custom_ops")
        if not raw:
            return []
        try:
            nodes = json.loads(raw)["nodes"]
        except (ValueError, TypeError, KeyError):
            raise ModelContractError("metadata key 'custom_ops': not a JSON object with a "
                                     "'nodes' list") from None
        if not isinstance(nodes, list) or not nodes or not all(
                isinstance(n, dict) and "op" in n for n in nodes):
            raise ModelContractError("metadata key 'custom_ops': 'nodes' must be a non-empty "
                                     "list of {op, ...} objects (absent key: no custom nodes)")
        return nodes

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
    if not (math.isfinite(c.sample_rate_hz) and 0 < c.sample_rate_hz <= MAX_RATE_HZ):
        bad("sample_rate_hz", f"must be a number in (0, {MAX_RATE_HZ:g}], got "
            f"{c.sample_rate_hz}")
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
    if c.state_mode == "carry" and c.model not in RECURRENT:
        bad("state_mode", f"carry mode needs a recurrent model ({', '.join(RECURRENT)}), "
                          f"not {c.model!r}")
    if c.model not in RECURRENT and (c.state_layers, c.state_hidden) != (1, 1):
        bad("state_layers", f"a {c.model} head's state is (1, batch, 1)")
    if c.model in MODALITY_MODELS and not c.modalities:
        bad("modalities", f"model {c.model!r} needs modalities")
    if c.model == "lstm" and c.modalities:
        bad("modalities", "model 'lstm' takes no modalities")
    if c.format_version < c.needed_format_version():
        what = ("model " + repr(c.model)) if c.model not in ("lstm", "linear") else (
            "'signals'" if c.signals else "'modalities'")
        bad("tactile.format_version", f"{c.format_version}, but {what} needs version "
                                      f"{c.needed_format_version()}")
    if not 1 <= c.preprocessing_version <= PREPROCESSING_VERSION:
        bad("preprocessing_version", f"{c.preprocessing_version}; this reader understands "
                                     f"1..{PREPROCESSING_VERSION}")
    if c.preprocessing_version != (2 if c.modalities else 1):
        bad("preprocessing_version", f"{c.preprocessing_version} with "
                                     f"{'' if c.modalities else 'no '}'modalities' (version 2 "
                                     "is the modalities' images, 1 the pen's features)")
    _validate_preprocessing(c.preprocessing, c.channels, bad)
    _validate_modalities(c, bad)
    if not isinstance(c.parity.get("passed"), bool):
        bad("parity", "needs a boolean 'passed'")
    if c.parity["passed"] is not True or (c.parity.get("native") or {}).get("passed") is False:
        bad("parity", "records a failed parity check (tactile-export writes no such file: it "
            "was edited)")
    odd = next((n for n in c.classes if any(ord(ch) < 32 or ord(ch) == 127 for ch in n)), None)
    if odd is not None:  # a label could not hold one (recordings' label rule): an edit
        bad("classes", f"{odd!r} holds a control character (a line break would split the "
            "label stream's lines)")
    if not c.package_version:
        bad("package_version", "must not be empty")


def _validate_preprocessing(p: dict, channels: tuple[str, ...], bad) -> None:
    key = "preprocessing"
    for name in ("mean", "std"):
        v = p.get(name)
        if not (isinstance(v, list) and len(v) == len(channels) and all(F.isnum(x) for x in v)):
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


def _validate_modalities(c: ModelContract, bad) -> None:
    """``signals`` and ``modalities`` against ``channels``, the rate, the window, the model."""
    channels = set(c.channels)
    owner: dict[str, str] = {}  # channel -> signal name
    signals = {}
    for s in c.signals:
        if s.name in signals or s.name in channels:
            bad("signals", f"signal name {s.name!r} is used twice (or is a channel's name)")
        signals[s.name] = s
        for ch in s.channels:
            if ch not in channels:
                bad("signals", f"signal {s.name!r}: {ch!r} is not among the channels")
            if ch in owner:
                bad("signals", f"channel {ch!r} is in signals {owner[ch]!r} and {s.name!r}")
            owner[ch] = s.name
        want = c.sample_rate_hz * len(s.channels)
        if not math.isclose(s.rate_hz, want, rel_tol=1e-6):
            bad("signals", f"signal {s.name!r}: rate_hz {s.rate_hz:g}, but {len(s.channels)} "
                           f"sub-samples per frame at {c.sample_rate_hz:g} Hz are {want:g} Hz")
    names, used = set(), {}
    for m in c.modalities:
        if m.name in names:
            bad("modalities", f"modality name {m.name!r} is used twice")
        names.add(m.name)
        for ch in m.channels:
            if ch not in channels:
                bad("modalities", f"modality {m.name!r}: {ch!r} is not among the channels")
            if ch in used:
                bad("modalities", f"channel {ch!r} is in modalities {used[ch]!r} and "
                                  f"{m.name!r}")
            used[ch] = m.name
        r = _sub_samples(m, owner, signals, lambda msg, n=m.name: bad("modalities",
                                                                      f"modality {n!r}: {msg}"))
        if not math.isclose(m.rate_hz, c.sample_rate_hz * r, rel_tol=1e-6):
            bad("modalities", f"modality {m.name!r}: rate_hz {m.rate_hz:g}, expected "
                              f"{c.sample_rate_hz * r:g}")
        if not 0 <= m.imfs <= MAX_IMFS:
            bad("modalities", f"modality {m.name!r}: imfs {m.imfs} not in 0..{MAX_IMFS}")
        if m.steps < 1 or -(-m.steps // r) > c.window:
            bad("modalities", f"modality {m.name!r}: steps {m.steps} must be 1..{c.window * r} "
                              f"(the window's {c.window} frames at {r} sample(s) per frame)")
        lo = 1 if c.model in CODED_MODELS else 0
        if m.atoms < lo or not lo <= m.nonzero <= max(m.atoms, lo):
            bad("modalities", f"modality {m.name!r}: atoms {m.atoms}, nonzero {m.nonzero}: "
                              f"need {lo} <= nonzero <= atoms" + (
                                  f" for model {c.model!r}" if lo else ""))
    if c.modalities and any(m.imfs for m in c.modalities):
        sifts = c.preprocessing.get("sifts")
        if not (isinstance(sifts, int) and not isinstance(sifts, bool) and sifts >= 1):
            bad("preprocessing", "'sifts' must be an integer >= 1 (the modalities' EMD sifts)")


def _sub_samples(m: ModalitySpec, owner: dict, signals: dict, bad) -> int:
    """Sub-samples per frame of modality ``m`` (1 for plain channels), checking that a signal
    modality is whole signals in their order, and a plain one no signal's sub-sample."""
    if not m.signal:
        taken = [ch for ch in m.channels if ch in owner]
        if taken:
            bad(f"{taken[0]!r} is a sub-sample of signal {owner[taken[0]]!r} (signal is false)")
        return 1
    rs, i = set(), 0
    while i < len(m.channels):
        name = owner.get(m.channels[i])
        if name is None:
            bad(f"{m.channels[i]!r} is in no signal (signal is true)")
        want = signals[name].channels
        if tuple(m.channels[i : i + len(want)]) != want:
            bad(f"signal {name!r} must appear whole, in time order: {list(want)}")
        rs.add(len(want))
        i += len(want)
    if len(rs) != 1:
        bad(f"its signals have different sub-sample counts {sorted(rs)}")
    return rs.pop()


def _signals(meta: Mapping[str, str]) -> tuple[SignalSpec, ...]:
    return tuple(SignalSpec(F.entry_field("signals", i, o, "name", "name"),
                            F.entry_field("signals", i, o, "channels", "names"),
                            F.entry_field("signals", i, o, "rate_hz", "rate"))
                 for i, o in enumerate(F.list_of_objects(meta, "signals")))


def _modalities(meta: Mapping[str, str]) -> tuple[ModalitySpec, ...]:
    out = []
    for i, o in enumerate(F.list_of_objects(meta, "modalities")):
        f = [("name", "name"), ("channels", "names"), ("signal", "bool"), ("rate_hz", "rate"),
             ("imfs", "int"), ("steps", "int"), ("atoms", "int"), ("nonzero", "int")]
        out.append(ModalitySpec(*(F.entry_field("modalities", i, o, n, k) for n, k in f)))
    return tuple(out)


def model_file(path: str | Path) -> Path:
    """``path`` as a model file to load: :class:`ModelContractError` (exit 3) when it is missing
    or a folder, with the same line in every command that loads a model."""
    if not str(path).strip():  # Path("") is "." (the current folder)
        raise ModelContractError("the model file's path is empty")
    path = Path(path)
    if path.is_dir():
        raise ModelContractError(f"{path}: a folder, not a model file (give the .onnx file)")
    if not path.is_file():
        raise ModelContractError(f"{path}: no such model file")
    return path


__all__ = [
    "FORMAT", "FORMAT_VERSION", "PREPROCESSING_VERSION", "OPSET", "INPUTS", "OUTPUTS", "BATCH",
    "FLOAT", "KEYS", "REQUIRED", "OPTIONAL", "STATE_MODES", "MODELS", "RECURRENT",
    "MODALITY_MODELS", "CODED_MODELS", "QUANTIZATIONS", "TensorSpec", "SignalSpec",
    "ModalitySpec", "ModelContract", "model_file",
    "IR_VERSION", "MAX_IMFS", "MAX_RATE_HZ", "MAX_SIFTS", "POSTPROCESS_PREFIX",
]

