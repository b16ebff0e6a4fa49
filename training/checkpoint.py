"""The run's files as data: the checkpoint (training -> export) and the resume state.

:func:`save_checkpoint` writes the checkpoint and :func:`load_checkpoint` reads it back;
:func:`save_resume` and :func:`load_resume` do the same for the resume state. Both are read
with ``torch.load(weights_only=True)`` (a checkpoint is data, never code) and then checked key
by key, because a file can come from anywhere: a wrong key gives one line naming the file and
the key (:class:`RecordingError`, exit 1), never a traceback.
"""

from __future__ import annotations

import io
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

import tactile
from tactile.device.recordings import Take
from tactile.errors import ConfigError, RecordingError, TactileError
from tactile.files import write_whole
from tactile.postprocess.metrics import WindowStream
from tactile.training.config import TrainConfig
from tactile.training.models import build_model

CHECKPOINT = "checkpoint.pt"
CHECKPOINT_FORMAT = "tactile-checkpoint"
CHECKPOINT_VERSION = 1
RESUME = "resume.pt"
RESUME_FORMAT = "tactile-resume"
RESUME_VERSION = 1
RUN_FILES = (CHECKPOINT, RESUME, "metrics.json")  # a folder holding one of these is a run
# what a saved config without these keys meant (they came later, or their default changed):
# the model before front ends, without the wide path, one model (no ensemble), stopped on the
# validation loss, no blended regression
SAVED_BEFORE = {"front": "none", "wide": False, "select": "loss", "ensemble": 1, "blend": "off"}
OLD_F_RNN = "an F-RNN saved before its input scale replaced batch normalisation: train it again"


def old_f_rnn(state: object, prefix: str = "") -> bool:
    """Whether ``state`` (a state dict; an F-RNN head's keys under ``prefix``) still holds the
    batch normalisations the F-RNN's input scale replaced (:data:`OLD_F_RNN`)."""
    return isinstance(state, dict) and f"{prefix}norms.0.weight" in state


@dataclass(frozen=True)
class Norm:
    """The normalisation a model is built with and its checkpoint keeps: ``mean``, ``std``
    (C,) float32 in the channels' units, from the training windows; ``emd_index`` the channels
    whose IMFs are features and ``center_index`` those whose window mean is removed (indices
    into the C channels; both empty for the granular models)."""

    mean: np.ndarray
    std: np.ndarray
    emd_index: list[int]
    center_index: list[int]


def plain(obj):
    """JSON- and weights_only-safe copy (numpy scalars to Python)."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def save_checkpoint(path: Path, cfg: TrainConfig, model: torch.nn.Module, metrics: dict, *,
                    classes: tuple[str, ...], takes: list[Take],
                    test: dict[int, tuple[int, int]], norm: Norm,
                    held_out: list | None = None, seen: tuple[int, ...] = ()) -> None:
    """Write the checkpoint ``path``: the weights of ``model``, the resolved ``cfg`` (whose
    ``channels`` are the model's inputs, in order), ``classes``, the channels' units and the
    sample rate (of ``takes``, the dataset's takes), ``norm``, the test split's rows (``test``:
    take index -> (first, end) rows) with each test take's fingerprint, the fingerprints of
    the takes training or validation read (``seen``: take indices), and ``metrics``; with
    ``held_out`` (a refit's run), the first training's label streams of the validation takes
    (:class:`~tactile.postprocess.metrics.WindowStream`: what the label stream's defaults
    are calibrated on, the final model having trained on those takes)."""
    channels = cfg.channels
    names = [t.path.name for t in takes]
    ck = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "package_version": tactile.__version__,
        "config": cfg.to_dict(),
        "classes": list(classes),
        "channels": list(channels),
        "units": [takes[0].info.channels[takes[0].channels.index(c)].unit for c in channels],
        "sample_rate_hz": takes[0].info.sample_rate_hz,
        "mean": norm.mean.tolist(),
        "std": norm.std.tolist(),
        "emd_index": norm.emd_index,
        "center_index": norm.center_index,
        # the high-rate signals centred whole (absent in older checkpoints: none)
        "center_groups": [list(g) for g in getattr(getattr(model, "pre", None),
                                                    "center_groups", [])],
        "test_rows": {names[i]: list(r) for i, r in test.items()},
        "test_fingerprints": {names[i]: takes[i].fingerprint() for i in test},
        "seen_fingerprints": sorted({takes[i].fingerprint() for i in seen}),
        "metrics": plain(metrics),
        "state_dict": model.state_dict(),
    }
    if held_out:
        ck["held_out_streams"] = [
            {"t": torch.from_numpy(np.asarray(s.t, np.float64)),
             "truth": torch.from_numpy(np.asarray(s.truth, np.int64)),
             "probs": torch.from_numpy(np.asarray(s.probs, np.float32))} for s in held_out]
    save_file(ck, path)


def save_file(obj: dict, path: Path) -> None:
    """``torch.save(obj)`` into ``path`` whole or not at all (serialised in memory, then
    :func:`~tactile.files.write_whole`): torch.save straight into the file left a cut-short
    file on a full disk and raised its own RuntimeError."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    write_whole(path, buf.getbuffer())


def _read(path: Path, what: str, hint: str) -> dict:
    if not path.is_file():
        raise RecordingError(f"{path}: no {what} ({hint})")
    try:  # torch.load does not test the archive's checksums: damaged bytes loaded as weights
        with zipfile.ZipFile(path) as z:
            damaged = z.testzip()
    except zipfile.BadZipFile:  # torch.save writes a zip archive; torch.load's own words for
        # one cut short or empty were a paragraph, EOFError, or a claim of foreign objects
        raise RecordingError(f"{path}: not a readable {what} (not the zip archive torch.save "
                             f"writes: empty, cut short or another file; "
                             f"{path.stat().st_size} bytes)") from None
    except OSError as e:
        raise RecordingError(f"{path}: cannot read ({e.strerror or e})") from None
    if damaged is not None:
        raise RecordingError(f"{path}: damaged ({damaged} fails its stored checksum): not a "
                             f"readable {what}")
    try:
        ck = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as e:  # noqa: BLE001  (any unpickling failure means "not a checkpoint")
        why = (str(e).splitlines() or [type(e).__name__])[0]
        if "weights only load failed" in why.lower():  # not torch's advice to unpickle it
            why = "it holds objects other than tensors and plain data, which are not loaded"
        raise RecordingError(f"{path}: not a readable {what} ({why})") from None
    if not isinstance(ck, dict):
        raise RecordingError(f"{path}: not a tactile {what} (a {type(ck).__name__})")
    return ck


def _names(v, n: int | None = None, at_least: int = 0) -> bool:
    return (isinstance(v, list) and all(isinstance(x, str) for x in v)
            and (n is None or len(v) == n) and len(v) >= at_least)


def _numbers(v, n: int) -> bool:
    return (isinstance(v, list) and len(v) == n and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
        for x in v))


def _indices(v, n: int) -> bool:
    return isinstance(v, list) and all(
        isinstance(x, int) and not isinstance(x, bool) and 0 <= x < n for x in v)


def _rows(v) -> bool:
    return isinstance(v, dict) and all(
        isinstance(k, str) and isinstance(r, list) and len(r) == 2
        and all(isinstance(x, int) for x in r) for k, r in v.items())


def check_checkpoint(ck: dict, path: Path) -> TrainConfig:
    """Validate a loaded checkpoint's keys; returns its config. Raises RecordingError naming
    ``path`` and the first bad key."""
    def bad(key: str, want: str) -> RecordingError:
        got = ck.get(key, None)
        shown = "missing" if key not in ck else f"got {type(got).__name__} {str(got)[:40]}"
        return RecordingError(f"{path}: checkpoint key {key!r}: must be {want} ({shown})")

    if ck.get("format") != CHECKPOINT_FORMAT:
        raise RecordingError(f"{path}: not a tactile checkpoint (format {ck.get('format')!r})")
    if ck.get("version") != CHECKPOINT_VERSION:
        raise RecordingError(f"{path}: checkpoint version {ck.get('version')!r}, this package "
                             f"reads {CHECKPOINT_VERSION}")
    if not isinstance(ck.get("config"), dict):
        raise bad("config", "a table of settings")
    try:
        cfg = TrainConfig.from_dict({**SAVED_BEFORE, **ck["config"]})
    except TactileError as e:
        raise RecordingError(f"{path}: checkpoint key 'config': {e}") from None
    if not _names(ck.get("classes"), at_least=2) or len(set(ck["classes"])) < len(
            ck["classes"]):
        raise bad("classes", "a list of at least 2 distinct class names")
    if not _names(ck.get("channels"), at_least=1) or len(set(ck["channels"])) < len(
            ck["channels"]):
        raise bad("channels", "a list of distinct channel names")
    n = len(ck["channels"])
    if cfg.channels and list(cfg.channels) != ck["channels"]:
        raise bad("channels", f"the config's channels {list(cfg.channels)}")
    checks = [
        ("units", _names(ck.get("units"), n), f"a list of {n} unit names"),
        ("sample_rate_hz", isinstance(ck.get("sample_rate_hz"), (int, float))
         and not isinstance(ck.get("sample_rate_hz"), bool) and ck["sample_rate_hz"] > 0,
         "a rate > 0"),
        ("mean", _numbers(ck.get("mean"), n), f"a list of {n} finite numbers"),
        ("std", _numbers(ck.get("std"), n) and all(x > 0 for x in ck["std"]),
         f"a list of {n} finite numbers > 0"),
        ("emd_index", _indices(ck.get("emd_index"), n), f"a list of channel indices < {n}"),
        ("center_index", _indices(ck.get("center_index"), n),
         f"a list of channel indices < {n}"),
        ("center_groups", isinstance(ck.get("center_groups", []), list) and all(
            _indices(g, n) and g for g in ck.get("center_groups", [])),
         f"a list of non-empty lists of channel indices < {n}"),
        ("test_rows", _rows(ck.get("test_rows", {})), "a table of take name -> [first, end]"),
        ("test_fingerprints", isinstance(ck.get("test_fingerprints", {}), dict) and all(
            isinstance(k, str) and isinstance(v, str)
            for k, v in ck.get("test_fingerprints", {}).items()),
         "a table of take name -> fingerprint"),
        ("seen_fingerprints", isinstance(ck.get("seen_fingerprints", []), list) and all(
            isinstance(v, str) for v in ck.get("seen_fingerprints", [])),
         "a list of fingerprints"),
        ("metrics", isinstance(ck.get("metrics", {}), dict), "a table"),
        ("state_dict", isinstance(ck.get("state_dict"), dict) and all(
            isinstance(k, str) and isinstance(v, torch.Tensor)
            for k, v in ck["state_dict"].items()), "a table of tensors"),
        ("held_out_streams", _streams(ck.get("held_out_streams", []), ck["classes"]),
         "a list of streams (t: finite, non-decreasing times; truth: class indices; probs: "
         "0..1, one column a class; one length, at least 1)"),
    ]
    for key, ok, want in checks:
        if not ok:
            raise bad(key, want)
    for name, t in ck["state_dict"].items():  # a model of NaN weights labels nothing
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise RecordingError(f"{path}: checkpoint key 'state_dict': {name} holds NaN or "
                                 "inf")
    if cfg.emd_channels and len(ck["emd_index"]) != len(cfg.emd_channels):
        raise bad("emd_index", f"{len(cfg.emd_channels)} indices (the config's emd_channels)")
    return cfg


def _streams(v: object, classes: list[str]) -> bool:
    """``held_out_streams``: a list of streams {t, truth, probs} (tensors) that make
    :class:`~tactile.postprocess.metrics.WindowStream` s of ``classes`` (which checks lengths,
    times and class indices), their probabilities in [0, 1]."""
    if not isinstance(v, list):
        return False
    for s in v:
        if not (isinstance(s, dict) and all(isinstance(s.get(x), torch.Tensor)
                                            for x in ("t", "truth", "probs"))):
            return False
        p = s["probs"]
        if not (p.is_floating_point() and bool(((p >= 0) & (p <= 1)).all())):  # (NaN: no)
            return False
        try:
            WindowStream(s["t"].numpy(), s["truth"].numpy(), p.numpy(), tuple(classes))
        except ConfigError:
            return False
    return True


def load_checkpoint(run_dir: Path):
    """Rebuild the model of a run from its checkpoint (data only: weights_only=True); returns
    (model in eval mode, the checkpoint dict). Every key is checked first
    (:func:`check_checkpoint`)."""
    path = Path(run_dir)
    path = path / CHECKPOINT if path.is_dir() else path
    ck = _read(path, "checkpoint", "train a run with tactile-train first")
    cfg = check_checkpoint(ck, path)
    try:
        model = build_model(cfg, len(ck["classes"]), torch.tensor(ck["mean"]),
                            torch.tensor(ck["std"]), channels=tuple(ck["channels"]),
                            rate_hz=float(ck["sample_rate_hz"]),
                            emd_index=list(ck["emd_index"]),
                            center_index=list(ck["center_index"]),
                            center_groups=ck.get("center_groups", []))
    except TactileError as e:  # modalities that do not fit the channels
        raise RecordingError(f"{path}: checkpoint key 'config': {e}") from None
    try:
        model.load_state_dict(ck["state_dict"])
    except RuntimeError as e:  # missing, unexpected or wrongly shaped weights
        if cfg.model == "f_rnn" and old_f_rnn(ck["state_dict"], "head."):
            raise RecordingError(f"{path}: {OLD_F_RNN} (its exported .onnx still runs)") from None
        first = " ".join(str(e).split())[:160]
        raise RecordingError(f"{path}: checkpoint key 'state_dict' does not fit its config "
                             f"({first})") from None
    model.eval()
    return model, ck


def save_resume(out: Path, cfg: TrainConfig, data: Path, world: int, state: dict) -> Path:
    """Write RUN/resume.pt: the config, the dataset's path, the process count and the state
    after the last finished epoch (tensors, numbers, lists: weights_only-safe)."""
    path = Path(out) / RESUME
    save_file({"format": RESUME_FORMAT, "version": RESUME_VERSION, "config": cfg.to_dict(),
               "data": str(Path(data).resolve()), "processes": world, "state": state}, path)
    return path


def load_resume(run_dir: Path) -> dict:
    """Read and check RUN/resume.pt (see :func:`save_resume`)."""
    run_dir = Path(run_dir)
    path = run_dir / RESUME
    if not path.is_file() and (run_dir / CHECKPOINT).is_file():
        raise RecordingError(f"{run_dir}: the run finished (no {RESUME}): nothing to resume")
    r = _read(path, "resume state", "only a run stopped with Ctrl-C has one")
    if r.get("format") != RESUME_FORMAT or r.get("version") != RESUME_VERSION:
        raise RecordingError(f"{path}: not a tactile resume state of version {RESUME_VERSION}")
    for key, kind in (("config", dict), ("data", str), ("state", dict)):
        if not isinstance(r.get(key), kind):
            raise RecordingError(f"{path}: key {key!r}: must be a {kind.__name__}")
    # a state saved before a key existed continues as it started (the newer default would
    # change the run half-way)
    r["config"] = {**SAVED_BEFORE, **r["config"]}
    if (r["config"].get("modalities") and r["config"].get("augment_gain", 0.3)
            and isinstance(r.get("state"), dict) and "augment_version" not in r["state"]):
        raise RecordingError(f"{path}: saved before granular models drew one gain per window "
                             "and modality (the run cannot go on as it started): train it again")
    try:
        TrainConfig.from_dict(r["config"])
    except TactileError as e:
        raise RecordingError(f"{path}: key 'config': {e}") from None
    state = r["state"]
    if state.get("phase") not in ("fit", "refit") or not isinstance(state.get("epoch"), int):
        raise RecordingError(f"{path}: key 'state': not a saved epoch")
    return r


__all__ = ["CHECKPOINT", "RESUME", "RUN_FILES", "Norm", "save_checkpoint", "load_checkpoint",
           "check_checkpoint", "save_resume", "load_resume", "plain"]
