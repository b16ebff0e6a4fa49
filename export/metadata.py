"""The contract of an exported model, filled from its checkpoint, and written into the file."""

from __future__ import annotations

import math

import onnx
import torch

import tactile
from tactile.contract import CODED_MODELS, ModalitySpec, ModelContract, SignalSpec
from tactile.export.graph import EXPORTER


def contract_for(ck: dict, parity: dict, quantization: str = "none",
                 source_run: str = "", model=None) -> ModelContract:
    """The :class:`ModelContract` of checkpoint ``ck`` with the measured ``parity`` figures.

    ``model`` (the checkpoint's model) gives the state's shape and, for a granular model, its
    resolved modalities (``layout``); without it the state comes from the config."""
    cfg = ck["config"]
    channels = list(ck["channels"])
    lstm = cfg["model"] == "lstm"
    emd = None
    if cfg.get("emd_channels"):
        emd = {"channels": list(cfg["emd_channels"]), "imfs": cfg["emd_imfs"],
               "sifts": cfg["emd_sifts"]}
    if model is not None:
        layers, hidden = model.state_shape
    else:
        layers, hidden = (int(cfg["layers"]), int(cfg["hidden"])) if lstm else (1, 1)
    layout = tuple(getattr(model, "layout", None) or ())
    signals, modalities = _granular(layout, channels, cfg["model"])
    high_rate = (_high_rate(cfg, channels, float(ck["sample_rate_hz"]))
                 if cfg["model"] in ("lstm", "linear") and not cfg.get("modalities") else [])
    if high_rate:
        signals = tuple(SignalSpec(h["signal"], tuple(h["channels"]), h["rate_hz"])
                        for h in high_rate)
    preprocessing = {
        "mean": [float(v) for v in ck["mean"]],
        "std": [float(v) for v in ck["std"]],
        "center": [channels[i] for i in ck.get("center_index", [])],
        "emd": emd,
    }
    groups = ck.get("center_groups") or []
    if groups:  # high-rate signals centred whole: one mean of all their samples in the window
        preprocessing["center"] = sorted({*preprocessing["center"],
                                          *(channels[i] for g in groups for i in g)},
                                         key=channels.index)
        preprocessing["center_groups"] = [[channels[i] for i in g] for g in groups]
    if modalities:
        preprocessing["sifts"] = int(cfg["emd_sifts"])
    if high_rate:
        preprocessing["high_rate"] = [{k: v for k, v in h.items() if k != "channels"}
                                      for h in high_rate]
    extra = {
        "exporter": f"{EXPORTER}; torch {torch.__version__}, onnx {onnx.__version__}",
        "training_config": _json(cfg),
    }
    if source_run:
        extra["source_run"] = source_run
    return ModelContract(
        classes=tuple(ck["classes"]),
        channels=tuple(channels),
        units=tuple(ck["units"]),
        sample_rate_hz=float(ck["sample_rate_hz"]),
        window=int(cfg["window"]),
        hop=int(cfg["hop"]),
        state_mode=cfg["state"],
        model=cfg["model"],
        state_layers=int(layers),
        state_hidden=int(hidden),
        preprocessing=preprocessing,
        package_version=tactile.__version__,
        training_metrics={**_metrics(ck.get("metrics", {})), **_blend(ck),
                          **_test_takes(ck), **_seen(ck)},
        parity=parity,
        quantization=quantization,
        extra=extra,
        signals=signals,
        modalities=modalities,
    )


def _granular(layout: tuple, channels: list[str], model: str
              ) -> tuple[tuple[SignalSpec, ...], tuple[ModalitySpec, ...]]:
    """The contract's signals and modalities from a granular model's resolved ``layout``
    (:class:`tactile.training.modality.ModalityLayout`: ``index`` into the channels,
    signal-major; ``units`` the signals' or channels' names). A coded model's ``nonzero`` is
    the count its coders use (scikit-learn's default when the config says 0); the others have
    no dictionary (atoms and nonzero 0)."""
    from tactile.training.sparse import default_n_nonzero

    signals, modalities = [], []
    for m in layout:
        names = tuple(channels[i] for i in m.index)
        if m.signal:
            for k, unit in enumerate(m.units):
                signals.append(SignalSpec(unit, names[k * m.r : (k + 1) * m.r], float(m.rate_hz)))
        coded = model in CODED_MODELS
        nonzero = (m.nonzero or default_n_nonzero(m.features, m.atoms)) if coded else 0
        modalities.append(ModalitySpec(m.name, names, bool(m.signal), float(m.rate_hz),
                                       int(m.imfs), int(m.steps), int(m.atoms) if coded else 0,
                                       int(nonzero)))
    return tuple(signals), tuple(modalities)


def _high_rate(cfg: dict, channels: list[str], rate_hz: float) -> list[dict]:
    """The high-rate signals a pen model takes at their own rate
    (``tactile.training.frontend.HighRateFront``: an ``lstm``'s spectral front in frames, a
    ``linear`` head over the whole window): per signal its name, sub-sample channels, rate,
    frame and hop (samples at that rate) and band edges (Hz); empty without signals or with
    an lstm's ``front='none'``."""
    from tactile.training.config import reads_signals, signals_from
    from tactile.training.frontend import band_edges_hz
    from tactile.training.modality import resolve_signals

    linear = cfg["model"] == "linear"
    if not reads_signals(cfg) or not cfg.get("signals"):
        return []
    out = []
    for name, names in resolve_signals(signals_from(cfg["signals"]), tuple(channels)):
        r = len(names)
        frame, hop = ((int(cfg["window"]) * r,) * 2 if linear else
                      (int(cfg["frame"]) * r, int(cfg["frame_hop"]) * r))
        out.append({"signal": name, "channels": list(names), "rate_hz": rate_hz * r,
                    "frame": frame, "hop": hop,
                    "bands_hz": [[lo, hi] for lo, hi in band_edges_hz(frame, rate_hz * r)]})
    return out


def _metrics(m: dict) -> dict:
    """The test figures worth carrying (the confusion matrix stays in the run folder)."""
    keep = ("windows", "accuracy", "recall", "shifted", "split", "split_windows", "val_accuracy",
            "best_epoch")
    return {k: _finite(m[k]) for k in keep if k in m}


def _blend(ck: dict) -> dict:
    """``{"blend": {c, mix, validation accuracies}}`` for a model with the blended
    regression (which reads every channel by itself, a high-rate signal's sub-samples too);
    else nothing."""
    b = (ck.get("metrics") or {}).get("blend")
    if not isinstance(b, dict):
        return {}
    keep = ("c", "mix", "val_acc", "regression_val_acc", "recurrent_val_acc")
    out = {k: _finite(b[k]) for k in keep if k in b}
    mix = (ck.get("state_dict") or {}).get("head.mix")
    if mix is not None:  # the weight the file computes with
        out["mix"] = float(mix)
    return {"blend": out}


def _test_takes(ck: dict) -> dict:
    """``{"test_takes": {take file name: {"rows": [start, end], "fingerprint": str or None}}}``:
    the run's test split, so that ``tactile-check --data`` can measure the same windows and
    recognise the takes by content (``None``: the run recorded no fingerprint); empty when the
    checkpoint names no test takes."""
    rows = ck.get("test_rows")
    if not isinstance(rows, dict) or not rows:
        return {}
    fps = ck.get("test_fingerprints")
    fps = fps if isinstance(fps, dict) else {}
    return {"test_takes": {str(n): {"rows": [int(v) for v in r], "fingerprint": (
        fps.get(n) if isinstance(fps.get(n), str) else None)} for n, r in rows.items()}}


def _seen(ck: dict) -> dict:
    """``{"seen_fingerprints": [...]}``: the takes the run trained or validated on, by content
    (:meth:`~tactile.device.recordings.Take.fingerprint`), so that ``tactile-check --data``
    says when its figure is on some of them; empty for a run that kept none."""
    seen = ck.get("seen_fingerprints")
    if not isinstance(seen, list) or not all(isinstance(v, str) for v in seen):
        return {}
    return {"seen_fingerprints": list(seen)}


def _finite(v):
    """JSON-safe: NaN/inf become None (strict JSON readers reject them)."""
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_finite(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _json(d: dict) -> str:
    import json

    return json.dumps(_finite(d), sort_keys=True)


def attach(model: onnx.ModelProto, contract: ModelContract) -> onnx.ModelProto:
    """Replace ``model``'s ``metadata_props`` with the contract's keys (in place; returned)."""
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, contract.to_metadata())
    return model


def metadata_of(model: onnx.ModelProto) -> dict[str, str]:
    return {p.key: p.value for p in model.metadata_props}
