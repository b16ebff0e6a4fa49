"""The training configuration: one frozen dataclass, validated when built.

Unknown keys and wrong types are errors (a typo must not silently train the default). The
resolved config travels in the checkpoint, so a run can always be rebuilt and exported.
"""

from __future__ import annotations

import dataclasses
import os
import re
import tomllib
import typing
from dataclasses import dataclass
from pathlib import Path

from tactile.cli import MAX_THREADS
from tactile.contract import MAX_IMFS, MODALITY_MODELS, MODELS
from tactile.device.recordings.summary import HOP, WINDOW
from tactile.errors import ConfigError

# The pen's emd_imfs / emd_sifts settings are capped below EMDConfig's own limits
# (tactile.contract.MAX_IMFS, MAX_SIFTS): a 50-sample window holds about log2(50) ~ 6 IMFs, and
# every sift runs on every window of every epoch, so larger values only cost training time.
MAX_EMD_IMFS = 8  # the emd_imfs setting's cap (a modality's imfs go to MAX_IMFS)
MAX_EMD_SIFTS = 50  # the emd_sifts setting's cap (also the modalities' sifts)
FRONTS = ("spectral", "none")
STATE_MODES = ("window", "carry")
SPLITS = ("user", "take", "time")
SCHEDULES = ("constant", "plateau", "cosine")
REFITS = ("auto", "on", "off")
BLENDS = ("auto", "on", "off")
BLENDED_MODELS = ("lstm", "f_rnn", "sf_rnn")
SELECTS = ("loss", "accuracy")
DEVICES = ("auto", "cpu", "cuda")
MAX_AUTO_THREADS = 4
# caps far above any use, so that a slip (hidden=10**20, layers=10**9) is one line naming the
# setting, not an overflow inside numpy or torch, or a model built layer by layer until the
# memory is gone
MAX_INT = 2**31 - 1  # every whole-number setting (seed: its own range)
MAX_SAMPLES = 1_000_000  # window, hop, frame_hop: samples
MAX_LAYERS = 64  # layers, ensemble
MAX_HIDDEN = 1_000_000  # (an allocation that large fails, in one line: out of memory)
MAX_ATOMS = 65_536  # a modality's dictionary atoms (and non-zeros per code)
FLOAT32_MAX = 3.4028234663852886e38  # the largest float32: lr and weight_decay reach the weights
# ``test`` / ``val`` selectors: FIELD:VALUE[,VALUE...] (see TrainConfig)
SELECTOR = re.compile(r"^(?P<field>[A-Za-z_][A-Za-z0-9_]*):(?P<values>.+)$")
# a signal's or a modality's name: it names ONNX metadata entries and run folders' tables
NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,31}$")


@dataclass(frozen=True)
class Modality:
    """One sensing modality of the granular models (a ``[modalities.NAME]`` table).

    ``channels``: shell-style patterns over the channel names and the high-rate signal names
    (a signal is one unit; the channels of a signal are not matched on their own); ``imfs``
    IMFs of EMD per channel or signal over the window at the modality's own rate (0: no EMD,
    the normalised values); ``steps`` samples at that rate in each step's data image;
    ``atoms`` of its sparse-coding dictionary (``sf_rnn``, ``sparse_linear``); ``nonzero``
    atoms per code (0: scikit-learn's default, a tenth of the image's features, at least 1).
    """

    name: str
    channels: tuple[str, ...]
    imfs: int = 0
    steps: int = 5
    atoms: int = 100
    nonzero: int = 0

    def __post_init__(self) -> None:
        where = f"modalities.{self.name}"
        if not isinstance(self.name, str) or not NAME.match(self.name):
            raise ConfigError(f"modality name {self.name!r}: must be a letter or _ then letters, "
                              "digits or _ (at most 32)")
        if not (isinstance(self.channels, tuple) and self.channels
                and all(isinstance(c, str) and c for c in self.channels)):
            raise ConfigError(f"{where}.channels={_shown(self.channels)}: must be a non-empty "
                              "list of channel or signal name patterns")
        for key, lo, hi in (("imfs", 0, MAX_IMFS), ("steps", 1, MAX_SAMPLES),
                            ("atoms", 1, MAX_ATOMS), ("nonzero", 0, MAX_ATOMS)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo or (
                    hi is not None and v > hi):
                want = f"{lo}..{hi}" if hi is not None else f">= {lo}"
                raise ConfigError(f"{where}.{key}={v!r}: must be an integer {want}")
        if self.nonzero > self.atoms:
            raise ConfigError(f"{where}.nonzero={self.nonzero}: must be at most atoms="
                              f"{self.atoms}")

    def to_dict(self) -> dict:
        return {"channels": list(self.channels), "imfs": self.imfs, "steps": self.steps,
                "atoms": self.atoms, "nonzero": self.nonzero}

    @classmethod
    def from_dict(cls, name: str, d) -> Modality:
        if not isinstance(d, dict):
            raise ConfigError(f"modalities.{name}={_shown(d)}: must be a table (channels, imfs, "
                              "steps, atoms, nonzero)")
        known = [f.name for f in dataclasses.fields(cls) if f.name != "name"]
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise ConfigError(f"modalities.{name}: unknown key(s) {unknown}; allowed: {known}")
        if "channels" not in d:
            raise ConfigError(f"modalities.{name}: give channels (name patterns)")
        ch = d["channels"]
        kw = {**d, "channels": tuple(ch) if isinstance(ch, list) else ch}
        return cls(name=name, **kw)


def _shown(v) -> str:
    text = repr(list(v) if isinstance(v, tuple) else v)
    return text if len(text) <= 60 else text[:57] + "..."


def signals_from(d) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """``[signals]`` (name -> list of channel name patterns) as the config holds it."""
    if isinstance(d, tuple):  # already the frozen form
        return d
    if not isinstance(d, dict):
        raise ConfigError(f"signals={_shown(d)}: must be a table of name = [channel patterns]")
    out = []
    for name, pats in d.items():
        if not isinstance(name, str) or not NAME.match(name):
            raise ConfigError(f"signals.{name}: a signal's name must be a letter or _ then "
                              "letters, digits or _ (at most 32)")
        if not (isinstance(pats, (list, tuple)) and pats
                and all(isinstance(p, str) and p for p in pats)):
            raise ConfigError(f"signals.{name}={_shown(pats)}: must be a non-empty list of "
                              "channel name patterns")
        out.append((name, tuple(pats)))
    return tuple(out)


def modalities_from(d) -> tuple[Modality, ...]:
    """``[modalities.NAME]`` tables as the config holds them, in the file's order."""
    if isinstance(d, tuple):
        return d
    if not isinstance(d, dict):
        raise ConfigError(f"modalities={_shown(d)}: must be tables [modalities.NAME]")
    return tuple(Modality.from_dict(name, m) for name, m in d.items())


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides a training run.

    Data: ``window`` samples per window, a new window every ``hop`` samples; ``channels`` picks
    and orders the input channels (empty: all the recordings have; a granular model's, those
    its modalities read). Splits: ``user`` keeps each
    user (the takes' ``user`` field, else each take) wholly in train, validation or test;
    ``take`` does the same per take; ``time`` puts the first ``1 - test_fraction`` of every take
    in training and the rest in test (for datasets with one take per class).

    Features: the normalised channels (those matching a ``center`` pattern minus their mean over
    the window, which removes offsets such as gravity on a tilted pen), plus ``emd_imfs`` IMFs
    of each of ``emd_channels`` (``emd_sifts`` sifts per IMF), as extra inputs at every step.

    Training multiplies each window's channels by random gains in ``1 +/- augment_gain`` (0: off),
    so that the model does not key on one user's signal levels, and adds to each window's
    uncentred channels random offsets in ``+/- augment_offset`` (in units of the channel's
    standard deviation; 0: off), so that it leans less on absolute levels that drift between
    sessions (granular models ignore it); an epoch is ``epoch_windows``
    training windows drawn at random without replacement (0 or more than there are: all of
    them; with ``state='carry'`` runs of ``carry_steps`` windows), and training stops when the
    validation figure ``select`` names has not improved for ``patience`` epochs (at most
    ``epochs``); the weights of its best epoch are kept. ``select``: ``accuracy`` (default), the
    highest validation accuracy, a lower validation loss breaking ties; ``loss``, the lowest
    validation loss (the loss can bottom out epochs before the accuracy does on a validation
    set unlike the training data: the model grows confident faster than it grows right). Options:
    ``schedule`` of the learning rate (``constant``, ``plateau``: halved when the validation loss
    stalls for ``patience // 4`` epochs, ``cosine``: down to ``lr / 100`` over ``epochs``),
    ``label_smoothing`` of the training targets, ``ema`` (the decay per step of an exponential
    moving average of the weights, which is what is validated and kept; 0: off) and ``refit``:
    ``on`` (default) trains again from scratch on training + validation windows for the best
    epoch count, ``auto`` does so with ``split='time'`` only, where the validation block is the
    recording just before the test block; ``off`` never.

    Model: ``lstm`` (``layers`` x ``hidden``, ``dropout``; with ``front='spectral'`` it runs over
    frames of ``frame`` samples every ``frame_hop``: the log power of each DFT bin and the mean
    of each feature, batch-normalised; ``none``: over the samples, as the pen paper; ``wide``
    (default on): a linear map of the mean over the window of what the LSTM reads is added to
    its logits, a direct path for the window's spectrum and levels; ``ensemble`` (default 1):
    that many such models, each from its own initial weights, trained side by side on the same
    batches, each on its own loss, whose probabilities are averaged: what is validated, kept
    and exported; ``blend``: ``auto`` (default) solves a logistic regression on whole-window
    features of the channels (mean, log standard deviation, log band energies) on all
    training windows at once, ``C`` chosen on the validation windows, and mixes its
    log-probabilities with the LSTM's at the weight that labels the most validation windows
    right (0 keeps the LSTM alone), the refit solving it again on training + validation
    windows; ``off``: the LSTM alone; ``on``: as ``auto``, and so also for ``f_rnn`` and
    ``sf_rnn``, which ``auto`` leaves as the granular-media paper has them) or
    ``linear`` (a linear classifier on the log energies of the IMFs, the granular-media paper's
    baseline; needs ``emd_channels``).
    The granular-media paper's models (``docs/granular.md``) work on ``modalities``, one
    :class:`Modality` per ``[modalities.NAME]`` table (name patterns over channels and signals,
    ``imfs``, ``steps``, ``atoms``, ``nonzero``): EMD of each modality over the window at its
    own rate, then a data image per step (one step per frame): ``sf_rnn`` (sparse codes of each
    modality's images over dictionaries learned from the training windows, fused by a fully
    connected layer, an LSTM of ``layers`` x ``hidden``), ``f_rnn`` (an LSTM per modality on
    its images, fused per step), ``sparse_linear`` (a linear classifier on the codes' mean
    magnitudes over the window) and, given modalities, ``linear`` (on the log energy of each
    IMF over the window). ``signals``: high-rate signals, ``[signals]`` name = [channel
    patterns]: the matching channels, in recording order, are the consecutive sub-samples of
    one signal per frame (the BioTac's ``f0_pac_00..21``: 2.2 kHz); empty: the takes' own
    ``signals`` declarations (every take must declare the same).
    ``state``: ``window`` classifies each window from a fresh state (the pen paper); ``carry``
    carries the LSTM state from window to window (needs ``hop == window``) and trains on runs of
    ``carry_steps`` consecutive windows.

    Named splits: ``test`` and ``val`` pick takes by a field of their JSON instead of the random
    draw: ``FIELD:VALUE[,VALUE...]``, where FIELD is ``name`` (the take's file name without
    extension) or any key of the take's JSON (``user``, ``trial``, ...) and each VALUE is a
    shell-style pattern (``name:*-rep5``, ``user:alice,bob``) or, for whole numbers, an
    inclusive range (``trial:41-50``). Empty (default): drawn at random from ``seed``.

    Machine: ``threads`` torch threads per process (0, the default: one per usable CPU minus
    one, at least 1 and at most :data:`MAX_AUTO_THREADS`, divided among the processes of a
    node under ``torchrun``); ``device``: ``auto`` (a GPU when there is one), ``cpu`` or
    ``cuda``.
    """

    window: int = WINDOW
    hop: int = HOP
    channels: tuple[str, ...] = ()
    center: tuple[str, ...] = ("accel_*", "gyro_*")
    emd_channels: tuple[str, ...] = ()
    emd_imfs: int = 4
    emd_sifts: int = 10
    signals: tuple[tuple[str, tuple[str, ...]], ...] = ()
    modalities: tuple[Modality, ...] = ()
    model: str = "lstm"
    front: str = "spectral"
    frame: int = 20
    frame_hop: int = 10
    layers: int = 2
    hidden: int = 64
    dropout: float = 0.4
    wide: bool = True
    ensemble: int = 1
    blend: str = "auto"
    state: str = "window"
    carry_steps: int = 8
    epochs: int = 150
    epoch_windows: int = 4096
    batch_size: int = 128
    lr: float = 3e-3
    weight_decay: float = 1e-4
    patience: int = 25
    select: str = "accuracy"
    schedule: str = "constant"
    label_smoothing: float = 0.0
    ema: float = 0.0
    refit: str = "on"
    augment_gain: float = 0.3
    augment_offset: float = 0.0
    split: str = "user"
    test_fraction: float = 0.3
    val_fraction: float = 0.2
    seed: int = 0
    test: str = ""
    val: str = ""
    threads: int = 0
    device: str = "auto"

    def __post_init__(self) -> None:
        _check_types(self)
        checks = [  # (holds, message, the fields it is about: the error shows their values)
            (4 <= self.window <= MAX_SAMPLES, f"window must be 4..{MAX_SAMPLES} samples",
             ("window",)),
            (1 <= self.hop <= MAX_SAMPLES, f"hop must be 1..{MAX_SAMPLES} samples", ("hop",)),
            (self.model in MODELS, f"model must be one of {', '.join(MODELS)}", ("model",)),
            (self.front in FRONTS, f"front must be one of {', '.join(FRONTS)}", ("front",)),
            (self.model != "lstm"
             or 2 <= self.frame <= self.window and 1 <= self.frame_hop <= MAX_SAMPLES,
             f"frame must be 2..window samples and frame_hop 1..{MAX_SAMPLES}",
             ("frame", "frame_hop", "window")),
            (self.epoch_windows >= 0, "epoch_windows must be >= 0 (0: every window)",
             ("epoch_windows",)),
            (self.state in STATE_MODES, f"state must be one of {', '.join(STATE_MODES)}",
             ("state",)),
            (self.split in SPLITS, f"split must be one of {', '.join(SPLITS)}", ("split",)),
            (self.schedule in SCHEDULES, f"schedule must be one of {', '.join(SCHEDULES)}",
             ("schedule",)),
            (0 <= self.label_smoothing < 1, "label_smoothing must be in [0, 1)",
             ("label_smoothing",)),
            (0 <= self.ema < 1, "ema must be in [0, 1) (0: off)", ("ema",)),
            (self.select in SELECTS, f"select must be one of {', '.join(SELECTS)}",
             ("select",)),
            (self.refit in REFITS, f"refit must be one of {', '.join(REFITS)}", ("refit",)),
            (self.blend in BLENDS, f"blend must be one of {', '.join(BLENDS)}", ("blend",)),
            (1 <= self.layers <= MAX_LAYERS and 1 <= self.hidden <= MAX_HIDDEN,
             f"layers must be 1..{MAX_LAYERS} and hidden 1..{MAX_HIDDEN}", ("layers", "hidden")),
            (0 <= self.dropout < 1, "dropout must be in [0, 1)", ("dropout",)),
            (1 <= self.ensemble <= MAX_LAYERS, f"ensemble must be 1..{MAX_LAYERS} (1: one model)",
             ("ensemble",)),
            (self.epochs >= 1 and self.batch_size >= 1 and self.patience >= 1,
             "epochs, batch_size and patience must be >= 1", ("epochs", "batch_size", "patience")),
            # (NaN fails too; the weights are float32, so the factors must be too)
            (0 < self.lr <= FLOAT32_MAX and 0 <= self.weight_decay <= FLOAT32_MAX,
             "lr must be > 0 and weight_decay >= 0, each within float32's range (3.4e38)",
             ("lr", "weight_decay")),
            (0 < self.test_fraction < 1, "test_fraction must be in (0, 1)", ("test_fraction",)),
            (0 < self.val_fraction < 1, "val_fraction must be in (0, 1)", ("val_fraction",)),
            (1 <= self.emd_imfs <= MAX_EMD_IMFS and 1 <= self.emd_sifts <= MAX_EMD_SIFTS,
             f"emd_imfs must be 1..{MAX_EMD_IMFS} and emd_sifts 1..{MAX_EMD_SIFTS}",
             ("emd_imfs", "emd_sifts")),
            (self.carry_steps >= 2, "carry_steps must be >= 2", ("carry_steps",)),
            (0 <= self.threads <= MAX_THREADS, f"threads must be 0..{MAX_THREADS} (0: automatic)",
             ("threads",)),
            (0 <= self.seed < 2**32, "seed must be in 0..4294967295 (numpy's range)", ("seed",)),
            (self.device in DEVICES, f"device must be one of {', '.join(DEVICES)}", ("device",)),
            (0 <= self.augment_gain < 1, "augment_gain must be in [0, 1)", ("augment_gain",)),
            (0 <= self.augment_offset <= 10, "augment_offset must be in [0, 10] (standard "
             "deviations; 0: off)", ("augment_offset",)),
        ]
        for ok, msg, fields in checks:
            if not ok:
                got = ", ".join(f"{k}={getattr(self, k)!r}" for k in fields)
                raise ConfigError(f"{msg} (got {got})")
        for key in ("test", "val"):
            spec = getattr(self, key)
            if spec and not SELECTOR.match(spec):
                raise ConfigError(
                    f"{key}={spec!r}: expected FIELD:VALUE[,VALUE...], e.g. 'user:alice,bob', "
                    "'trial:41-50' or 'name:*-rep5'")
        if (self.test or self.val) and self.split == "time":
            raise ConfigError("test/val name takes; split='time' splits every take in time: "
                              "use split='user' or 'take' with them")
        if self.state == "carry" and self.hop != self.window:
            raise ConfigError(
                f"state='carry' needs hop == window (got hop={self.hop}, window={self.window}): "
                "a carried state must see every sample once"
            )
        if self.state == "carry" and self.model != "lstm":
            raise ConfigError("state='carry' needs model='lstm'")
        if self.blend == "on" and self.model not in BLENDED_MODELS:
            raise ConfigError(f"blend='on' needs a recurrent model ({', '.join(BLENDED_MODELS)}; "
                              f"got model={self.model!r})")
        if self.ensemble > 1 and self.model != "lstm":
            raise ConfigError(f"ensemble={self.ensemble} needs model='lstm' (got "
                              f"model={self.model!r})")
        if self.model == "linear" and not (self.emd_channels or self.modalities):
            raise ConfigError("model='linear' classifies EMD features: give emd_channels or "
                              "[modalities.NAME] tables")
        if self.model in MODALITY_MODELS and not self.modalities:
            raise ConfigError(f"model={self.model!r} needs modalities: give at least one "
                              "[modalities.NAME] table (channels, imfs, steps, atoms)")
        if self.modalities and self.emd_channels:
            raise ConfigError(f"emd_channels={list(self.emd_channels)} is for the pen's models: "
                              "with modalities, set imfs per modality")
        if self.modalities and self.model == "lstm":
            raise ConfigError("modalities are for model='sf_rnn', 'f_rnn', 'sparse_linear' or "
                              "'linear' (got model='lstm')")
        for key in ("channels", "emd_channels"):  # a channel twice: the file cannot name it
            seen = getattr(self, key)
            twice = sorted({c for c in seen if seen.count(c) > 1})
            if twice:
                raise ConfigError(f"{key}: {twice[0]!r} given twice (got {key}={list(seen)})")
        names = [n for n, _ in self.signals]
        for what, seen in (("signal", names), ("modality", [m.name for m in self.modalities])):
            twice = sorted({n for n in seen if seen.count(n) > 1})
            if twice:
                raise ConfigError(f"{what} {twice[0]!r} named twice")

    @property
    def blends(self) -> bool:
        """Whether the model has the blended regression: ``blend='on'``, or ``'auto'`` with
        ``model='lstm'`` (the granular-media paper's models stay as published)."""
        return self.blend == "on" or (self.blend == "auto" and self.model == "lstm")

    @property
    def refits(self) -> bool:
        """Whether training ends with a refit on training + validation windows."""
        return self.refit == "on" or (self.refit == "auto" and self.split == "time")

    def to_dict(self) -> dict:
        """Plain data (TOML's shapes): lists, and for ``signals`` / ``modalities`` tables
        (dicts in the config's order); :meth:`from_dict` reads it back."""
        out = {f.name: (list(v) if isinstance(v, tuple) else v)
               for f in dataclasses.fields(self) for v in [getattr(self, f.name)]}
        out["signals"] = {name: list(pats) for name, pats in self.signals}
        out["modalities"] = {m.name: m.to_dict() for m in self.modalities}
        return out

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"unknown config key(s) {unknown}; allowed: {sorted(known)}")
        kw = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        if "signals" in d:
            kw["signals"] = signals_from(d["signals"])
        if "modalities" in d:
            kw["modalities"] = modalities_from(d["modalities"])
        return cls(**kw)

    @classmethod
    def from_toml(cls, path: Path) -> TrainConfig:
        try:
            text = Path(path).read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise ConfigError(f"{path}: not UTF-8 text (a TOML file is)") from None
        except OSError as e:
            raise ConfigError(f"{path}: {e.strerror or e}") from None
        try:
            return cls.from_dict(tomllib.loads(text))
        except (tomllib.TOMLDecodeError, ConfigError) as e:  # the file named, with the key
            raise ConfigError(f"{path}: {e}") from None

    def replace(self, **kw) -> TrainConfig:
        return self.from_dict({**self.to_dict(), **kw})


def reads_signals(config) -> bool:
    """Whether a model reads its high-rate signals at their own rate, sub-samples in time
    order: a granular model (``modalities``), a ``linear`` head, a spectral front. An lstm with
    ``front='none'`` reads a signal's sub-samples as plain channels, so ``[signals]`` means
    nothing to it. ``config``: a :class:`TrainConfig` or a checkpoint's config dict (one saved
    before ``front`` existed has no spectral front)."""
    get = config.get if isinstance(config, dict) else (lambda k: getattr(config, k))
    return bool(get("modalities")) or get("model") == "linear" or get("front") == "spectral"


def unused(cfg: TrainConfig) -> list[str]:
    """The settings ``cfg`` moves from their defaults that its model or options never read,
    each as ``key=value (why)``: a training that ran as if they were not there would
    otherwise say nothing of them."""
    base = TrainConfig()
    rules = [  # (keys, when they are not read, why)
        (("front", "frame", "frame_hop", "wide"), cfg.model != "lstm", "only model='lstm'"),
        (("blend",), cfg.model not in BLENDED_MODELS, "only model='lstm', 'f_rnn' or 'sf_rnn'"),
        (("frame", "frame_hop"), cfg.model == "lstm" and cfg.front != "spectral",
         "only front='spectral'"),
        (("hidden", "layers", "dropout"), cfg.model in ("linear", "sparse_linear"),
         f"model={cfg.model!r} has no LSTM"),
        (("emd_imfs",), not cfg.emd_channels,
         "only with emd_channels; a modality sets its own imfs" if cfg.modalities
         else "only with emd_channels"),
        (("emd_sifts",), not (cfg.emd_channels or cfg.modalities),
         "only with emd_channels or modalities"),
        (("carry_steps",), cfg.state != "carry", "only state='carry'"),
        (("center", "augment_offset"), bool(cfg.modalities),
         "the granular models read neither"),
        (("test_fraction",), bool(cfg.test), f"test={cfg.test!r} names the test takes"),
        (("val_fraction",), bool(cfg.val), f"val={cfg.val!r} names the validation takes"),
        (("signals",), not reads_signals(cfg),
         "front='none' reads a signal's sub-samples as plain channels"),
    ]
    said: dict[str, str] = {}
    for keys, idle, why in rules:
        for k in keys:
            if idle and k not in said and getattr(cfg, k) != getattr(base, k):
                value = cfg.to_dict()[k] if k == "signals" else getattr(cfg, k)
                said[k] = f"{k}={value!r} ({why})"
    return list(said.values())


def _check_types(cfg: TrainConfig) -> None:
    hints = typing.get_type_hints(type(cfg))
    for f in dataclasses.fields(cfg):
        value, hint = getattr(cfg, f.name), hints[f.name]
        if f.name in ("signals", "modalities"):  # checked when read (signals_from, Modality)
            ok = isinstance(value, tuple) and all(
                isinstance(v, Modality) if f.name == "modalities" else
                isinstance(v, tuple) and len(v) == 2 for v in value)
            want = "tables (see TrainConfig)"
        elif typing.get_origin(hint) is tuple:
            ok = isinstance(value, tuple) and all(isinstance(v, str) for v in value)
            want = "a list of names"
        elif hint is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            want = "a number"
        else:
            ok = isinstance(value, hint) and not (hint is int and isinstance(value, bool))
            want = hint.__name__
            if ok and hint is int and f.name != "seed" and abs(value) > MAX_INT:
                ok, want = False, f"a whole number within +-{MAX_INT}"
        if not ok:
            raise ConfigError(f"config {f.name}={value!r}: must be {want}")


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask, which containers and ``taskset`` set)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def resolve_threads(threads: int, procs_per_node: int = 1, cpus: int | None = None) -> int:
    """The torch threads of one process: ``threads`` when > 0; 0 (automatic) gives each of the
    node's ``procs_per_node`` processes an equal share of the usable CPUs minus one (left to
    the rest of the machine), at least 1 and at most :data:`MAX_AUTO_THREADS` (an LSTM of this
    size gains little past that). On a 2-CPU machine: 1."""
    if threads > 0:
        return threads
    cpus = usable_cpus() if cpus is None else cpus
    return max(1, min(MAX_AUTO_THREADS, (cpus - 1) // max(1, procs_per_node)))


def apply_threads(n: int) -> int:
    """Make torch use ``n`` intra-op threads and ``n`` inter-op threads in this process; returns
    ``n``. Every command that runs torch calls it before its first tensor operation (the
    inter-op count can be set only then; later calls keep the first one)."""
    import torch

    torch.set_num_threads(n)
    try:
        torch.set_num_interop_threads(n)
    except RuntimeError:  # already set, or parallel work already started: keep it
        pass
    return n


def resolve_device(device: str, cuda_available: bool | None = None) -> str:
    """``auto`` -> ``cuda`` when a GPU is there, else ``cpu``; ``cuda`` without one is an
    error (a run that asked for a GPU must not quietly train for hours on a CPU)."""
    if cuda_available is None:
        import torch

        cuda_available = torch.cuda.is_available()
    if device == "auto":
        return "cuda" if cuda_available else "cpu"
    if device == "cuda" and not cuda_available:
        raise ConfigError("device='cuda' but torch sees no GPU (use device='auto' or 'cpu')")
    return device


__all__ = ["TrainConfig", "Modality", "unused", "MODELS", "FRONTS", "STATE_MODES",
           "SPLITS", "SCHEDULES", "SELECTS", "REFITS", "BLENDS", "BLENDED_MODELS", "DEVICES",
           "signals_from", "modalities_from", "reads_signals",
           "apply_threads", "resolve_threads", "resolve_device", "usable_cpus"]
