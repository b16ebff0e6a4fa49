"""What training works on, made ready once: the takes checked, split and cut into windows,
the normalisation fitted on the training windows, then every window's features.

Features have no trainable part, so they are computed once, up front (EMD, or a granular
model's data images, dictionaries and sparse codes), and the loop trains the head on them.
Under torchrun each process computes a slice and all of them receive the whole.
"""

from __future__ import annotations

import fnmatch
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from tactile.device.recordings import Take
from tactile.device.recordings.take_meta import signal_order_differs
from tactile.errors import ConfigError, RecordingError
from tactile.postprocess.smoothing import UNCERTAIN
from tactile.training import feature_pass
from tactile.training.checkpoint import Norm
from tactile.training.config import TrainConfig, reads_signals, unused
from tactile.training.data import (
    Split,
    Windows,
    channel_stats,
    classes_of,
    name_list,
    pick_channels,
    split_windows,
)
from tactile.training.dist import Dist
from tactile.training.granular import learn_dictionaries, pooled_stats
from tactile.training.log import Log
from tactile.training.modality import (
    literal_signals,
    partial_signals,
    recorded_order,
    resolve,
    resolve_signals,
    signals_of_takes,
)
from tactile.training.model import Classifier


@dataclass(frozen=True)
class Prepared:
    """A dataset ready to train on: ``cfg`` resolved (its ``channels`` the model's inputs, in
    order; the high-rate ``signals`` as exact names), the ``takes`` and ``classes``, the
    ``split`` (its ``test`` rows and ``description``), the windows of each part (``parts``:
    ``train``, ``val``, ``test`` -> :class:`Windows`) and the normalisation (``norm``)."""

    cfg: TrainConfig
    takes: list[Take]
    classes: tuple[str, ...]
    split: Split
    parts: dict[str, Windows]
    norm: Norm


def check_inputs(data: Path, takes: list[Take],
                 cfg: TrainConfig) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The classes and the input channels of ``takes`` (the dataset ``data``); at least two
    classes, none named ``uncertain`` (the label stream's unsettled label), and
    ``emd_channels`` among the inputs, else one line naming what is wrong. A granular model
    with no ``channels`` setting takes the channels its modalities read (:func:`modality_inputs`),
    not all the takes have."""
    classes = classes_of(takes)
    if len(classes) < 2:
        raise RecordingError(f"{data}: only one label ({classes[0]}); need at least two classes")
    if UNCERTAIN in classes:
        raise ConfigError(f"{data}: a class is named {UNCERTAIN!r}, the name the label stream "
                          "reserves for no stable label: rename its takes' label")
    channels = pick_channels(takes[0], cfg.channels)
    if cfg.modalities and not cfg.channels:
        channels = modality_inputs(takes, channels, cfg)
    missing = [c for c in cfg.emd_channels if c not in channels]
    if missing:
        raise ConfigError(f"emd_channels {missing} not among the input channels {list(channels)}")
    return classes, channels



def signals_for(takes: list[Take], channels: tuple[str, ...],
                cfg: TrainConfig) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """The high-rate signals among ``channels``: the config's ``[signals]`` patterns (each
    signal's channels in recording order), else the ones the takes declare."""
    if not cfg.signals:
        return signals_of_takes(takes, channels)
    order = recorded_order(takes, channels)  # a signal's sub-samples in recording order
    return tuple((n, tuple(sorted(c, key=order.index)))
                 for n, c in resolve_signals(cfg.signals, order))


def modality_inputs(takes: list[Take], channels: tuple[str, ...],
                    cfg: TrainConfig) -> tuple[str, ...]:
    """The channels of ``channels`` that ``cfg``'s modalities read, in their order: a granular
    model's inputs when its config names no ``channels``, so that it runs on a device that
    sends only those (a BioTac model of one finger on that finger's channels)."""
    signals = signals_for(takes, channels, cfg)
    layout = resolve(cfg.replace(channels=channels, signals=literal_signals(signals)), channels,
                     takes[0].info.sample_rate_hz)
    used = set().union(*(m.index for m in layout))
    return tuple(c for i, c in enumerate(channels) if i in used)


def _check_classes(parts: dict, classes: tuple[str, ...], log: Log) -> None:
    """Every class in the training windows (else an error: the model could never say it);
    a class missing from the validation or test windows is named in a warning (the figures
    there leave it out)."""
    for part in ("train", "val", "test"):
        absent = [c for k, c in enumerate(classes) if not (parts[part].y == k).any()]
        if not absent:
            continue
        if part == "train":
            raise ConfigError(f"class(es) {absent} have no training window in this split: "
                              "each class needs takes (users) in training; record more, or "
                              "name the test/validation takes (test=..., val=...)")
        log.warn(f"class(es) {absent} have no {'validation' if part == 'val' else 'test'} "
                 f"window in this split: its figures leave them out")


def prepare(takes: list[Take], classes: tuple[str, ...], channels: tuple[str, ...],
            cfg: TrainConfig, log: Log, dist: Dist) -> Prepared:
    """Resolve the modalities (if any), split and cut the windows, fit the normalisation on
    the training windows (rank 0's, shared: every process normalises alike)."""
    idle = unused(cfg)
    if idle:
        log.warn(f"settings this training does not read: {'; '.join(idle)}")
    signals = ()
    partial = (partial_signals(takes, channels) if reads_signals(cfg) and not cfg.signals
               else [])
    if partial:
        log.warn(f"channels holds some but not all sub-samples of the takes' signal"
                 f"{'s' * (len(partial) > 1)} {', '.join(partial)}: read as plain channels at "
                 f"{takes[0].info.sample_rate_hz:g} Hz, not as the signal (select all of them to "
                 "read it at its own rate)")
    if cfg.modalities:  # the high-rate signals as exact names, then the layout (fail early)
        narrowed = not cfg.channels and len(channels) < len(takes[0].channels)
        if narrowed:  # (check_inputs kept the channels the modalities read)
            log.info(f"channels: the {len(channels)} the modalities read, of the takes' "
                     f"{len(takes[0].channels)} (set channels=... to choose others)")
            # the signals among those (a [signals] entry that no modality reads names
            # channels no longer there: left out, not an error)
            kept = set(channels)
            signals = tuple((n, c) for n, c in signals_for(takes, takes[0].channels, cfg)
                            if set(c) <= kept)
        else:
            signals = signals_for(takes, channels, cfg)
        cfg = cfg.replace(channels=channels, signals=literal_signals(signals))
        layout = resolve(cfg, channels, takes[0].info.sample_rate_hz)
        log.info("modalities: " + "; ".join(
            f"{m.name} {', '.join(m.units)} ({m.rate_hz:g} Hz, {m.features} features)"
            for m in layout))
    else:
        cfg = cfg.replace(channels=channels)
        if reads_signals(cfg):  # signals at their own rate
            signals = signals_for(takes, channels, cfg)
            if signals:
                cfg = cfg.replace(signals=literal_signals(signals))
                log.info("high-rate signals: " + "; ".join(
                    f"{n} ({len(c)} sub-samples a frame, "
                    f"{takes[0].info.sample_rate_hz * len(c):g} Hz)" for n, c in signals))
    for take in takes:  # [signals] reads sub-samples in recording order: no take may disagree
        differs = signal_order_differs(take.meta.get("signals", {}), signals, "the config's")
        if differs:
            raise ConfigError(f"{take.path.name}: {differs}; [signals] takes a signal's channels "
                              "in the order the takes record them")
    split, parts = split_windows(takes, classes, channels, cfg)
    log.info(f"classes {list(classes)}; windows train {len(parts['train'])}, "
             f"val {len(parts['val'])}, test {len(parts['test'])}; split {split.description}")
    if split.shared:
        log.warn(split.shared)
    _check_classes(parts, classes, log)
    # statistics fitted once (rank 0) and shared: every process normalises alike
    stats = (pooled_stats(parts["train"].x, channels, signals) if cfg.modalities or signals
             else channel_stats(parts["train"]))
    mean, std = dist.broadcast(*stats)
    emd_index = [channels.index(c) for c in cfg.emd_channels]
    center_index = [] if cfg.modalities else centered(channels, cfg.center)
    if not cfg.modalities:
        log_center(log, channels, cfg.center, center_index,
                   cfg.center == TrainConfig().center)
        whole = [n for n, names in signals if set(names) & {channels[i] for i in center_index}]
        if whole:  # (the model centres them: training/model.py, TextureModel)
            log.info(f"center: {', '.join(whole)} as whole signals (one mean of all their "
                     "samples in the window, not one per sub-sample)")
    return Prepared(cfg, takes, classes, split, parts, Norm(mean, std, emd_index, center_index))


def centered(channels: tuple[str, ...], patterns: tuple[str, ...]) -> list[int]:
    """Indices of the channels matching any ``center`` pattern (shell-style, e.g. ``accel_*``)."""
    return [i for i, c in enumerate(channels) if any(fnmatch.fnmatchcase(c, p) for p in patterns)]


def log_center(log: Log, channels: tuple[str, ...], patterns: tuple[str, ...],
               index: list[int], default: bool = False) -> None:
    """Say which channels the ``center`` patterns matched; warn when patterns a user set match
    none (a misspelt name). The defaults name the pen's IMU: on another sensor they match
    nothing, which is said, not warned of (centring is no setting to reach for there)."""
    if not patterns:
        log.info("center: none (no patterns)")
    elif not index and default:
        log.info(f"center: none (the defaults {', '.join(patterns)}, the pen's IMU, match none "
                 "of these channels)")
    elif not index:
        log.warn(f"center patterns {', '.join(patterns)} match none of the channels "
                 f"{name_list(list(channels), 8)}: no channel is centred (set center=... to "
                 "choose some, or center= for none)")
    else:
        log.info(f"center ({', '.join(patterns)}): {', '.join(channels[i] for i in index)}")


def features(model: Classifier, parts: dict[str, Windows], seed: int, log: Log,
             dist: Dist) -> dict[str, torch.Tensor]:
    """Every part's features (N, S, F) by ``model.pre``, once. A granular model's
    preprocessing that ``needs_dictionaries`` goes in three steps: the data images, the
    dictionaries learned from the training images (seeded with ``seed``), then the codes."""
    coded = getattr(model.pre, "needs_dictionaries", False)
    if len(getattr(model.pre, "emds", ())) or coded:  # (an F-RNN has EMD, no codes)
        log.info(f"{'EMD and sparse codes' if coded else 'EMD'} in float64 by "
                 f"{feature_pass.backend()}")
    with feature_pass.feature_pass():
        return _features_exact(model, parts, seed, log, dist)


def _features_exact(model: Classifier, parts: dict[str, Windows], seed: int, log: Log,
                    dist: Dist) -> dict[str, torch.Tensor]:
    if not getattr(model.pre, "needs_dictionaries", False):
        return {k: _features(model.pre, w, log, k, dist) for k, w in parts.items()}
    images = {k: _features(model.pre.images, w, log, f"images {k}", dist)
              for k, w in parts.items()}
    t1 = time.perf_counter()
    rows = learn_dictionaries(model.pre, images["train"], seed, dist)
    log.info(f"dictionaries learned from {rows} training image rows in "
             f"{time.perf_counter() - t1:.1f} s")
    # 32 windows (1,472 image rows) a call: OMP's (rows, steps, atoms) temporaries stay in
    # cache; 512 a call took 1.9x the CPU time (13.9 against 7.2 ms a BioTac window)
    return {k: _apply(model.pre.post, v, log, f"codes {k}", dist, chunk=32)
            for k, v in images.items()}


def _features(fn, w: Windows, log: Log, name: str, dist: Dist) -> torch.Tensor:
    """``fn`` (the model's ``pre``, or a stage of it) on every window: (N, T', F), computed
    once (no trainable part); under DDP each process computes a slice and all of them
    receive the whole."""
    return _apply(fn, torch.from_numpy(w.x), log, f"features {name}", dist)


def _apply(fn, x: torch.Tensor, log: Log, desc: str, dist: Dist,
           chunk: int = 512) -> torch.Tensor:
    """``fn`` over the rows of ``x`` in chunks, each process its :meth:`Dist.slice`."""
    lo, hi = dist.slice(len(x))
    with torch.no_grad():
        shape = fn(x[:1]).shape[1:]  # the output's shape per row, for an empty slice too
        chunks = [torch.zeros(0, *shape)]
        for i in tqdm(range(lo, hi, chunk), desc=desc, disable=not log.bars, leave=False,
                      file=sys.stderr):
            chunks.append(fn(x[i : min(i + chunk, hi)]))
    return dist.gather(torch.cat(chunks), len(x))


__all__ = ["Prepared", "check_inputs", "modality_inputs", "signals_for", "prepare", "centered",
           "log_center", "features"]
