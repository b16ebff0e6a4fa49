"""Train a classifier on a dataset folder and write an evaluated run: tactile-train DATA --out RUN.

Reads top to bottom: load takes -> split by user/take/time -> cut windows -> normalisation from
the training windows -> features (EMD once, up front) -> train with Adam and early stopping on
the validation split -> evaluate on the test split -> write RUN/:

    checkpoint.pt     weights + resolved config + classes, channels, rate, normalisation,
                      test rows and metrics (torch.load(weights_only=True) reads it)
    metrics.json      the figures; confusion.txt the paper-style table;
    curves.png, confusion.png
    resume.pt         only after Ctrl-C: the state to continue from (tactile-train --resume RUN)

Under ``torchrun`` the same command trains data-parallel (:mod:`tactile.training.dist`): every
process takes its share of each epoch's windows, rank 0 alone prints and writes RUN/.
"""

from __future__ import annotations

import argparse
import copy
import fnmatch
import json
import math
import random
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.optim.lr_scheduler import ReduceLROnPlateau
from tqdm import tqdm

import tactile
from tactile.cli import Parser, add_debug, run
from tactile.device.recordings import load_dataset
from tactile.errors import ConfigError, RecordingError
from tactile.training.checkpoint import (
    CHECKPOINT,
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    OLD_F_RNN,
    RESUME,
    load_checkpoint,
    load_resume,
    old_f_rnn,
    save_resume,
)
from tactile.training.config import (
    TrainConfig,
    apply_threads,
    resolve_device,
    resolve_threads,
    usable_cpus,
)
from tactile.training.data import (
    Windows,
    channel_index,
    channel_stats,
    classes_of,
    concat,
    name_list,
    split_windows,
)
from tactile.training.dist import Dist
from tactile.training.evaluate import (
    _runs,
    per_take,
    predict,
    shifted,
    shifted_line,
    summary,
    table,
)
from tactile.training.granular import learn_dictionaries, pooled_stats
from tactile.training.modality import literal_signals, resolve, resolve_signals, signals_of_takes
from tactile.training.model import TextureModel, build_model, member_loss
from tactile.training.sampling import epoch_order

AUGMENT_VERSION = 2
"""The gain augmentation a resume state was saved with: 2 draws one gain per window and
modality for granular models (before, per window and feature; the pen's is unchanged)."""
EXIT_INTERRUPTED = 130  # the shell's code for a command ended by SIGINT
RUN_FILES = (CHECKPOINT, RESUME, "metrics.json")  # a folder holding one of these is a run


class Log:
    """Diagnostics on stderr. ``info`` only with progress on (and on rank 0); ``warn`` always
    (rank 0). ``bars``: tqdm bars on a terminal; elsewhere (a log file, CI) a plain line per
    epoch instead, never escape codes."""

    def __init__(self, progress: bool, main: bool = True) -> None:
        self.progress, self.main = progress and main, main
        self.bars = self.progress and sys.stderr.isatty()

    def info(self, msg: str) -> None:
        if self.progress:
            print(msg, file=sys.stderr, flush=True)

    def warn(self, msg: str) -> None:
        if self.main:
            print(f"warning: {msg}", file=sys.stderr, flush=True)


class Stop:
    """SIGINT while training: noted, and the loop stops at the next batch (``requested``),
    rolls back to the last finished epoch and saves. Used as a context manager around the
    epochs; outside it SIGINT is Python's KeyboardInterrupt."""

    def __init__(self, dist: Dist) -> None:
        self.dist, self.flag, self._old = dist, False, None

    def __enter__(self) -> Stop:
        self._old = signal.signal(signal.SIGINT, self._note)
        return self

    def __exit__(self, *exc) -> None:
        signal.signal(signal.SIGINT, self._old)

    def _note(self, signum, frame) -> None:
        self.flag = True

    def requested(self) -> bool:
        """Whether to stop now; under DDP every process agrees (any one's SIGINT stops all)."""
        return self.dist.any(self.flag)


class Context:
    """What the training loop needs besides the model and the data."""

    def __init__(self, cfg: TrainConfig, log: Log, dist: Dist, device: torch.device,
                 stop: Stop | None, on_epoch: Callable[[str, int], None] | None) -> None:
        self.cfg, self.log, self.dist, self.device = cfg, log, dist, device
        self.stop, self.on_epoch = stop, on_epoch
        self.snapshot: dict | None = None  # the state after the last finished epoch
        self.fit_history: dict | None = None  # the first phase's, once a refit runs
        self.fit_best: dict | None = None  # the first phase's best weights, during a refit
        self._unroll: Unroll | None = None

    def unroll(self, head: nn.Module) -> Unroll:
        """One :class:`Unroll` of ``head`` for the whole run (DDP wraps it once)."""
        if self._unroll is None:
            self._unroll = Unroll(head)
        return self._unroll


class Unroll(nn.Module):
    """The head over S consecutive windows, its state carried from each to the next:
    (B, S, T, F) features + state (L, B, H) x 2 -> logits (B, S, classes) (an ensemble in
    training mode: (B, S, members, classes)). One forward pass
    per batch, so that DistributedDataParallel sees one forward per backward."""

    def __init__(self, head: nn.Module) -> None:
        super().__init__()
        self.head = head

    def forward(self, f: torch.Tensor, h: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        out = []
        for k in range(f.shape[1]):
            logits, h, c = self.head(f[:, k], h, c)
            out.append(logits)
        return torch.stack(out, 1)


class Interrupted(Exception):
    """Raised inside the loop when a stop was requested; :func:`train` saves and returns."""


def train(data: Path, out: Path, cfg: TrainConfig, progress: bool = True, *,
          resume: dict | None = None,
          on_epoch: Callable[[str, int], None] | None = None) -> dict:
    """Train, evaluate and save a run; returns the metrics (``interrupted`` True when SIGINT
    stopped it: RUN/ then holds the best checkpoint so far and ``resume.pt``).

    ``resume``: the state :func:`load_resume` read, to continue an interrupted run (``cfg``
    must be its config). ``on_epoch(phase, epoch)``: called after each finished epoch (1-based;
    phase ``fit`` or ``refit``), after its state is saved in memory."""
    t_start = time.perf_counter()
    dist = Dist.from_env()
    log = Log(progress, dist.is_main)
    threads = apply_threads(resolve_threads(cfg.threads, dist.local_world))
    device = dist.device(resolve_device(cfg.device))
    dist.start(device)
    _seed(cfg.seed)
    takes = load_dataset(data)
    classes = classes_of(takes)
    if len(classes) < 2:
        raise RecordingError(f"{data}: only one label ({classes[0]}); need at least two classes")
    channels = tuple(takes[0].channels[i] for i in channel_index(takes[0], cfg.channels))
    missing = [c for c in cfg.emd_channels if c not in channels]
    if missing:
        raise ConfigError(f"emd_channels {missing} not among the input channels {list(channels)}")
    # said once the data is known to fit: a bad input's error is then the only line
    job = f"; {dist.world} processes in all (rank 0 writes)" if dist.world > 1 else ""
    log.info(f"threads {threads} per process ({'set' if cfg.threads else 'automatic'}; "
             f"{usable_cpus()} usable CPUs, {dist.local_world} process(es) here); device "
             f"{device}{job}")
    signals = ()
    if cfg.modalities:  # the high-rate signals as exact names, then the layout (fail early)
        signals = (resolve_signals(cfg.signals, channels) if cfg.signals
                   else signals_of_takes(takes, channels))
        cfg = cfg.replace(channels=channels, signals=literal_signals(signals))
        layout = resolve(cfg, channels, takes[0].info.sample_rate_hz)
        log.info("modalities: " + "; ".join(
            f"{m.name} {', '.join(m.units)} ({m.rate_hz:g} Hz, {m.features} features)"
            for m in layout))
    else:
        cfg = cfg.replace(channels=channels)
    split, parts = split_windows(takes, classes, channels, cfg)
    log.info(f"classes {list(classes)}; windows train {len(parts['train'])}, "
             f"val {len(parts['val'])}, test {len(parts['test'])}; split {split.description}")
    # statistics fitted once (rank 0) and shared: every process normalises alike
    stats = (pooled_stats(parts["train"].x, channels, signals) if cfg.modalities
             else channel_stats(parts["train"]))
    mean, std = dist.broadcast(*stats)
    emd_index = [channels.index(c) for c in cfg.emd_channels]
    center_index = [] if cfg.modalities else centered(channels, cfg.center)
    if not cfg.modalities:
        _log_center(log, channels, cfg.center, center_index)
    model = build_model(cfg, len(classes), torch.from_numpy(mean), torch.from_numpy(std),
                        channels=channels, rate_hz=takes[0].info.sample_rate_hz,
                        emd_index=emd_index, center_index=center_index)
    t0 = time.perf_counter()
    if getattr(model.pre, "needs_dictionaries", False):  # images, dictionaries, then codes
        images = {k: _features(model.pre.images, w, log, f"images {k}", dist)
                  for k, w in parts.items()}
        t1 = time.perf_counter()
        rows = learn_dictionaries(model.pre, images["train"], cfg.seed, dist)
        log.info(f"dictionaries learned from {rows} training image rows in "
                 f"{time.perf_counter() - t1:.1f} s")
        # 32 windows (1,472 image rows) a call: OMP's (rows, steps, atoms) temporaries stay in
        # cache; 512 a call took 1.9x the CPU time (13.9 against 7.2 ms a BioTac window)
        feats = {k: _apply(model.pre.post, v, log, f"codes {k}", dist, chunk=32)
                 for k, v in images.items()}
        del images
    else:
        feats = {k: _features(model.pre, w, log, k, dist) for k, w in parts.items()}
    model.fit_features(feats["train"])  # what the head keeps of them (an F-RNN's input scale)
    feature_s = time.perf_counter() - t0
    model.to(device)
    ctx = Context(cfg, log, dist, device, None, on_epoch)
    norm = dict(mean=mean, std=std, emd_index=emd_index, center_index=center_index)
    # Ctrl-C stops at the next batch; after the last epoch it is only noted (the run is saved)
    with Stop(dist) as ctx.stop:
        try:
            history = _fit(model, parts, feats, ctx, resume)
        except Interrupted:
            model.to("cpu")
            saved = _save_interrupted(out, data, cfg, model, ctx, parts, feats, classes, takes,
                                      split, norm) if dist.is_main else {"interrupted": True}
            dist.barrier()  # the others wait for rank 0's files: torchrun ends a failed job
            dist.finish()
            return saved
        model.to("cpu")
        dist.finish()
        if not dist.is_main:
            return {"interrupted": False}
        metrics = _test_metrics(model, parts, feats, takes, classes)
        metrics["shifted"] = shifted(model, takes, classes, channels, split.test, cfg.window,
                                     cfg.hop, takes[0].info.sample_rate_hz)
        metrics.update(
            classes=list(classes), channels=list(channels), split=split.description,
            split_windows={k: len(w) for k, w in parts.items()},
            best_epoch=history["best_epoch"],
            val_accuracy=history["val_acc"][history["best_epoch"]],
            refit_epochs=history.get("refit_epochs", 0),
            epochs_run=len(history["train_loss"]), centered=[channels[i] for i in center_index],
            feature_seconds=round(feature_s, 1),
            train_seconds=round(time.perf_counter() - t_start, 1),
            threads=threads, device=str(device), processes=dist.world, seed=cfg.seed,
            interrupted=False,
        )
        _write_run(out, cfg, model, metrics, history, classes, takes, split, norm)
        (out / RESUME).unlink(missing_ok=True)  # finished: nothing left to resume
    return metrics


def _test_metrics(model: TextureModel, parts: dict, feats: dict, takes, classes) -> dict:
    """Window and per-take figures on the test split."""
    probs = predict(model, parts["test"], feats=feats["test"])
    metrics = summary(parts["test"].y, probs, classes)
    metrics.update(per_take(parts["test"], probs, [t.path.stem for t in takes]))
    return metrics


def centered(channels: tuple[str, ...], patterns: tuple[str, ...]) -> list[int]:
    """Indices of the channels matching any ``center`` pattern (shell-style, e.g. ``accel_*``)."""
    return [i for i, c in enumerate(channels) if any(fnmatch.fnmatchcase(c, p) for p in patterns)]


def _log_center(log: Log, channels: tuple[str, ...], patterns: tuple[str, ...],
                index: list[int]) -> None:
    """Say which channels the ``center`` patterns matched; warn when a set of patterns matches
    none (the defaults name the pen's IMU: on another sensor nothing would be centred)."""
    if not patterns:
        log.info("center: none (no patterns)")
    elif not index:
        log.warn(f"center patterns {', '.join(patterns)} match none of the channels "
                 f"{name_list(list(channels), 8)}: no channel is centred (set center=... to "
                 "choose some, or center= for none)")
    else:
        log.info(f"center ({', '.join(patterns)}): {', '.join(channels[i] for i in index)}")


def _seed(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


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


def _sequences(w: Windows, steps: int) -> np.ndarray:
    """(S, steps) row indices of consecutive windows within one run (carried-state training)."""
    seqs = []
    for rows in _runs(w):
        for i in range(0, len(rows) - steps + 1, steps):
            seqs.append(rows[i : i + steps])
    if not seqs:
        raise ConfigError(f"no run holds {steps} consecutive windows: lower carry_steps")
    return np.stack(seqs)


def _fit(model: TextureModel, parts: dict, feats: dict, ctx: Context,
         resume: dict | None = None) -> dict:
    """Train with early stopping on the validation split; with ``refit``, then train the head
    again from a fresh start on the training and validation windows together, for as many
    epochs as the best validation epoch took (the final model has seen the validation data).
    ``resume``: the state saved at an interruption, in either phase."""
    cfg = model.cfg
    if resume is None or resume["phase"] == "fit":
        history = _train(model, parts["train"], feats["train"], cfg.epochs, ctx,
                         val=(parts["val"], feats["val"]), resume=resume)
    else:
        history = resume["fit_history"]
    if cfg.refits:
        epochs = history["best_epoch"] + 1
        ctx.fit_history, ctx.fit_best = history, copy.deepcopy(model.head.state_dict())
        if resume is None or resume["phase"] == "fit":
            ctx.log.info(f"refit on training + validation windows for {epochs} epoch"
                         f"{'s' if epochs != 1 else ''}")
            torch.manual_seed(cfg.seed)
            for m in model.head.modules():
                if m is not model.head and hasattr(m, "reset_parameters"):
                    m.reset_parameters()
            resume = None
        else:
            ctx.fit_best = resume["fit_best"]
        _train(model, concat(parts["train"], parts["val"]),
               torch.cat([feats["train"], feats["val"]]), epochs, ctx, resume=resume)
        history["refit_epochs"] = epochs
    return history


def _epoch_order(units: np.ndarray, per_epoch: int, gen: torch.Generator) -> np.ndarray:
    """The training units (window rows, or (S, steps) runs of rows) of one epoch, in the order
    they are visited: ``per_epoch`` of them (0: every one once) drawn with ``gen`` (the same on
    every process); :func:`tactile.training.sampling.epoch_order`."""
    return epoch_order(units, per_epoch, gen)


def _train(model: TextureModel, w: Windows, f_all: torch.Tensor, n_epochs: int, ctx: Context,
           val: tuple[Windows, torch.Tensor] | None = None, resume: dict | None = None) -> dict:
    """Adam on the windows ``w`` (features ``f_all``) for at most ``n_epochs``. With ``val``:
    early stopping on its accuracy or loss (``select``), and the best epoch's weights are kept;
    without: the last's.
    ``resume``: continue from the state saved after an epoch (weights, optimiser, schedule,
    random generators, early-stopping counters, history)."""
    cfg, dist, dev = ctx.cfg, ctx.dist, ctx.device
    head = model.head
    # the head unrolled over a unit's windows; under torchrun in DDP (gradients averaged)
    step = dist.wrap(ctx.unroll(head), dev)
    opt = torch.optim.Adam(head.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = _scheduler(opt, cfg, n_epochs)
    loss_fn = nn.CrossEntropyLoss(label_smoothing=cfg.label_smoothing)
    val_loss_fn = nn.CrossEntropyLoss()  # unsmoothed: early stopping compares true fits
    y_train = torch.from_numpy(w.y).long()
    # units of training, (U, S) window rows: S consecutive windows whose state is carried
    # (state='carry'), else one window each (S = 1)
    units = _sequences(w, cfg.carry_steps) if cfg.state == "carry" else np.arange(len(w))[:, None]
    gen = torch.Generator().manual_seed(cfg.seed)  # the epoch's order: alike on every process
    aug = torch.Generator().manual_seed(cfg.seed + 7919 * dist.rank)  # gains: one per process
    batch = math.ceil(cfg.batch_size / dist.world)  # per process: the global batch stays
    offset = model.offset_scale()  # (F,) or None
    phase = "fit" if val is not None else "refit"
    s = {"epoch": 0, "best": math.inf, "best_acc": -1.0, "best_state": None, "stale": 0,
         "history": {"train_loss": [], "val_loss": [], "val_acc": [], "best_epoch": 0},
         # exponential moving average of the weights, updated every step (None: off)
         "ema": {k: v.detach().clone() for k, v in head.state_dict().items()}
         if cfg.ema else None}
    if resume is not None:
        s = _restore(resume, head, opt, sched, gen, aug)
    history, ema = s["history"], s["ema"]
    epochs = tqdm(range(s["epoch"], n_epochs), desc=phase, disable=not ctx.log.bars,
                  file=sys.stderr, initial=s["epoch"], total=n_epochs)
    for epoch in epochs:
        t_epoch = time.perf_counter()
        model.train()
        order = dist.shard(_epoch_order(units, cfg.epoch_windows, gen))
        total, count = 0.0, 0
        for i in tqdm(range(0, len(order), batch), desc=f"epoch {epoch + 1}",
                      disable=not ctx.log.bars, leave=False, file=sys.stderr):
            if ctx.stop is not None and ctx.stop.requested():
                raise Interrupted
            rows = order[i : i + batch]  # (B, S)
            f = f_all[rows].to(dev)  # (B, S, T, F)
            if cfg.augment_gain:  # random gains per window: the model's augment_gain
                f = model.augment_gain(f, cfg.augment_gain, aug)
            if offset is not None:  # then random offsets per window on the uncentred channels
                f = _augment_offset(f, offset, aug)
            h, c = (t.to(dev) for t in model.zero_state(len(rows)))
            # (B, S, classes), an ensemble's (B, S, members, classes): every window's loss
            logits = step(f, h, c)
            loss = member_loss(loss_fn, logits, y_train[rows].to(dev))
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(head.parameters(), 5.0)
            opt.step()
            if ema is not None:
                with torch.no_grad():
                    for k, v in head.state_dict().items():
                        if v.is_floating_point():  # not a step counter (batch norm's)
                            ema[k].mul_(cfg.ema).add_(v, alpha=1 - cfg.ema)
            total += float(loss.detach()) / cfg.ensemble * len(rows)  # members' mean
            count += len(rows)
        total, count = dist.sum(total, count)
        history["train_loss"].append(total / count)
        line = f"{phase} epoch {epoch + 1}/{n_epochs}: train loss {total / count:.3f}"
        stop = False
        if val is None:  # (a plateau schedule needs a validation loss: the rate stays)
            if sched is not None and not isinstance(sched, ReduceLROnPlateau):
                sched.step()
        else:
            stop, line = _validate(model, val, val_loss_fn, sched, ema, s, epoch, epochs, line,
                                   dist)
        s["epoch"] = epoch + 1
        if not ctx.log.bars:  # a log file or CI: one plain line per epoch
            ctx.log.info(f"{line} ({time.perf_counter() - t_epoch:.1f} s)")
        ctx.snapshot = _snapshot(phase, s, head, opt, sched, gen, aug, ctx)
        if ctx.on_epoch is not None:
            ctx.on_epoch(phase, epoch + 1)
        if stop:
            ctx.log.info(f"early stop after epoch {epoch + 1}: best epoch "
                         f"{history['best_epoch'] + 1}")
            break
    if val is not None:
        head.load_state_dict(s["best_state"])
    elif ema is not None:
        head.load_state_dict(ema)
    return history


def _augment_offset(f: torch.Tensor, offset: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """A batch's features (B, S, T, F) plus, per window and feature, a random offset uniform in
    ``+/- offset`` ((F,) half-widths, the model's ``offset_scale``), constant over the
    window's T steps. Drawn from ``gen`` on the CPU after the gains (without offsets the draws
    are those of earlier versions)."""
    shape = (*f.shape[:2], 1, f.shape[-1])  # (B, S, 1, F)
    return f + (offset * (2 * torch.rand(shape, generator=gen) - 1)).to(f.device)


def _validate(model, val, val_loss_fn, sched, ema, s: dict, epoch: int, bar,
              line: str, dist: Dist) -> tuple[bool, str]:
    """One epoch's validation: the loss and accuracy (of the averaged weights with ``ema``),
    the schedule's step, the best weights so far; returns (stop early?, the epoch's line).
    Under torchrun every process validates rank 0's model and takes rank 0's figures, so that
    all of them keep the same best epoch and stop together."""
    head, cfg, history = model.head, model.cfg, s["history"]
    dist.sync_buffers(head)
    if ema is not None:  # validate (and keep) the averaged weights
        live = {k: v.clone() for k, v in head.state_dict().items()}
        head.load_state_dict(ema)
    probs = predict(model, val[0], feats=val[1])
    val_loss = float(val_loss_fn(torch.log(torch.from_numpy(probs) + 1e-9),
                                 torch.from_numpy(val[0].y).long()))
    val_acc = float((probs.argmax(1) == val[0].y).mean())
    val_loss, val_acc = (float(v) for v in dist.broadcast(np.array([val_loss, val_acc]))[0])
    history["val_loss"].append(val_loss)
    history["val_acc"].append(val_acc)
    bar.set_postfix(loss=f"{history['train_loss'][-1]:.3f}", val_loss=f"{val_loss:.3f}",
                    val_acc=f"{val_acc:.3f}")
    if isinstance(sched, ReduceLROnPlateau):
        sched.step(val_loss)
    elif sched is not None:
        sched.step()
    if _improves(cfg.select, val_acc, val_loss, s):
        s["best"], s["best_acc"], s["stale"] = val_loss, val_acc, 0
        history["best_epoch"] = epoch
        s["best_state"] = {k: v.clone() for k, v in head.state_dict().items()}
    else:
        s["stale"] += 1
    if ema is not None:
        head.load_state_dict(live)
    return s["stale"] >= cfg.patience, (f"{line}, val loss {val_loss:.3f}, val acc {val_acc:.3f}"
                                        f"{' (best)' if s['stale'] == 0 else ''}")


def _improves(select: str, val_acc: float, val_loss: float, s: dict) -> bool:
    """Whether this epoch beats the best so far: ``loss``, a validation loss lower by more than
    1e-4; ``accuracy``, a higher validation accuracy, or the same with such a lower loss."""
    lower = val_loss < s["best"] - 1e-4
    if select == "loss":
        return lower
    best_acc = s.get("best_acc", -1.0)
    return val_acc > best_acc + 1e-9 or (abs(val_acc - best_acc) <= 1e-9 and lower)


def _scheduler(opt: torch.optim.Optimizer, cfg: TrainConfig, n_epochs: int):
    """The learning-rate schedule of ``cfg.schedule`` (None: constant ``lr``)."""
    if cfg.schedule == "plateau":  # halve the rate when validation loss stalls
        return ReduceLROnPlateau(
            opt, factor=0.5, patience=max(1, cfg.patience // 4))
    if cfg.schedule == "cosine":  # from lr down to lr / 100 over the epochs
        return torch.optim.lr_scheduler.CosineAnnealingLR(opt, n_epochs, eta_min=cfg.lr / 100)
    return None


# --- resuming: the state after an epoch, as plain tensors and lists (weights_only-safe) -------

def _rng_state(gen: torch.Generator, aug: torch.Generator) -> dict:
    name, keys, pos, has_gauss, gauss = np.random.get_state()
    version, internal, py_gauss = random.getstate()
    state = {"torch": torch.get_rng_state(), "order": gen.get_state(), "gain": aug.get_state(),
             "numpy": [name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss),
                       float(gauss)],
             "python": [version, list(internal), py_gauss]}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict, gen: torch.Generator, aug: torch.Generator) -> None:
    torch.set_rng_state(state["torch"])
    gen.set_state(state["order"])
    aug.set_state(state["gain"])
    name, keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
    version, internal, py_gauss = state["python"]
    random.setstate((version, tuple(internal), py_gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _snapshot(phase: str, s: dict, head: nn.Module, opt, sched, gen, aug, ctx: Context) -> dict:
    """Everything an epoch boundary knows, copied (training goes on changing the live ones)."""
    return copy.deepcopy({
        "phase": phase, **s, "head": head.state_dict(), "opt": opt.state_dict(),
        "sched": sched.state_dict() if sched is not None else None,
        "rng": _rng_state(gen, aug), "fit_history": ctx.fit_history, "fit_best": ctx.fit_best,
        "augment_version": AUGMENT_VERSION,
    })


def _restore(r: dict, head: nn.Module, opt, sched, gen, aug) -> dict:
    """Put the saved state back; a state that does not fit (edited, or from another version)
    is a RecordingError, not a traceback."""
    try:
        head.load_state_dict(r["head"])
        opt.load_state_dict(r["opt"])
        if sched is not None:
            sched.load_state_dict(r["sched"])
        _set_rng_state(r["rng"], gen, aug)
        state = {k: copy.deepcopy(r[k]) for k in ("epoch", "best", "best_state", "stale",
                                                  "history", "ema")}
        state["best_acc"] = float(r.get("best_acc", -1.0))  # absent from older resume files
        return state
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as e:
        if old_f_rnn(r.get("head")):
            raise RecordingError(f"{RESUME}: {OLD_F_RNN}") from None
        first = " ".join(str(e).split())[:120]
        raise RecordingError(f"{RESUME}: the saved state does not fit this run "
                             f"({type(e).__name__}: {first})") from None


def _save_interrupted(out: Path, data: Path, cfg: TrainConfig, model: TextureModel,
                      ctx: Context, parts: dict, feats: dict, classes, takes, split,
                      norm: dict) -> dict:
    """After SIGINT: RUN/resume.pt (the state after the last finished epoch), and the best
    weights so far as an ordinary run (checkpoint, test metrics marked ``interrupted``)."""
    snap = ctx.snapshot
    if snap is None:
        ctx.log.warn("interrupted before the first epoch ended: nothing to save")
        return {"interrupted": True, "epochs_run": 0}
    out.mkdir(parents=True, exist_ok=True)
    save_resume(out, cfg, data, ctx.dist.world, snap)
    if snap["phase"] == "fit":
        best, history = snap["best_state"] or snap["head"], snap["history"]
    else:  # a refit stopped half-way: the first phase's best model is the best there is
        best, history = snap["fit_best"], snap["fit_history"]
    model.head.load_state_dict(best)
    metrics = _test_metrics(model, parts, feats, takes, classes)
    metrics.update(
        classes=list(classes), channels=list(cfg.channels), split=split.description,
        split_windows={k: len(w) for k, w in parts.items()}, best_epoch=history["best_epoch"],
        val_accuracy=history["val_acc"][history["best_epoch"]] if history["val_acc"] else None,
        epochs_run=len(history["train_loss"]), phase=snap["phase"], interrupted=True,
        shifted=None, seed=cfg.seed,
    )
    _write_run(out, cfg, model, metrics, history, classes, takes, split, norm)
    ctx.log.warn(f"interrupted: {snap['phase']} epoch {snap['epoch']} was the last finished; "
                 f"best checkpoint so far in {out / CHECKPOINT}; continue with "
                 f"tactile-train --resume {out}")
    return metrics


def _write_run(out: Path, cfg: TrainConfig, model: TextureModel, metrics: dict, history: dict,
               classes: tuple[str, ...], takes, split, norm: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
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
        "mean": norm["mean"].tolist(),
        "std": norm["std"].tolist(),
        "emd_index": norm["emd_index"],
        "center_index": norm["center_index"],
        "test_rows": {names[i]: list(r) for i, r in split.test.items()},
        "test_fingerprints": {names[i]: takes[i].fingerprint() for i in split.test},
        "metrics": _plain(metrics),
        "state_dict": model.state_dict(),
    }
    torch.save(ck, out / CHECKPOINT)
    (out / "metrics.json").write_text(json.dumps(_plain(metrics), indent=1) + "\n")
    (out / "confusion.txt").write_text(table(metrics, classes, "test split") + "\n")
    _plots(out, history, metrics, classes)


def _plots(out: Path, history: dict, metrics: dict, classes: tuple[str, ...]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ep = np.arange(1, len(history["train_loss"]) + 1)
    best = history["best_epoch"] + 1
    ax[0].plot(ep, history["train_loss"], label="train")
    ax[0].plot(ep[: len(history["val_loss"])], history["val_loss"], label="validation")
    ax[0].set(xlabel="epoch", ylabel="cross-entropy", title="loss")
    ax[1].plot(ep[: len(history["val_acc"])], history["val_acc"])
    ax[1].set(xlabel="epoch", ylabel="accuracy", title="validation accuracy", ylim=(0, 1))
    for a in ax:  # the epoch whose weights were kept
        a.axvline(best, color="tab:red", linestyle="--", linewidth=1, label=f"best epoch {best}")
    ax[0].legend()
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=100)
    plt.close(fig)
    counts = np.array(metrics["confusion"])
    norm = np.array(metrics["confusion_normalised"])
    fig, ax = plt.subplots(figsize=(1.4 * len(classes) + 2, 1.0 * len(classes) + 1.5))
    ax.imshow(norm, vmin=0, vmax=1, cmap="Blues")
    for i in range(len(classes)):
        for j in range(len(classes)):  # the share of the row, and the count it is made of
            ax.text(j, i, f"{norm[i, j]:.2f}\n({counts[i, j]})", ha="center", va="center",
                    fontsize=8, color="white" if norm[i, j] > 0.5 else "black")
    ax.set_xticks(range(len(classes)), classes, rotation=30, ha="right")
    ax.set_yticks(range(len(classes)), classes)
    ax.set(xlabel="estimated class", ylabel="label of input data",
           title=f"test accuracy {metrics['accuracy']:.3f} (share of row, window count)")
    fig.tight_layout()
    fig.savefig(out / "confusion.png", dpi=100)
    plt.close(fig)


def _plain(obj):
    """JSON- and weights_only-safe copy (numpy scalars to Python)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-train", description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path, nargs="?",
                   help="dataset folder (takes: .csv + .json); with --resume, default: the "
                        "run's own")
    p.add_argument("--out", type=Path, help="run folder to write (must not hold a run)")
    p.add_argument("--config", type=Path, help="TOML file of settings (see TrainConfig)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting, e.g. --set hidden=32 --set emd_channels=accel_z")
    p.add_argument("--resume", type=Path, metavar="RUN",
                   help="continue the run that Ctrl-C stopped, with its own settings")
    p.add_argument("--force", action="store_true", help="overwrite the run in --out")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_debug(p)
    return p


def parse_sets(pairs: list[str], base: TrainConfig) -> TrainConfig:
    """``key=value`` overrides, typed like the field they set."""
    d = base.to_dict()
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise ConfigError(f"--set {pair!r}: expected KEY=VALUE")
        if key not in d:
            raise ConfigError(f"--set {key}: unknown setting; allowed: {sorted(d)}")
        if key in ("signals", "modalities"):
            raise ConfigError(f"--set {key}: a table ([{key}...]): give it in the --config file")
        current = getattr(TrainConfig, key)
        try:
            if isinstance(current, tuple):
                d[key] = [v for v in value.split(",") if v]
            elif isinstance(current, bool):
                d[key] = {"true": True, "on": True, "1": True,
                          "false": False, "off": False, "0": False}[value.lower()]
            elif isinstance(current, int):
                d[key] = int(value)
            elif isinstance(current, float):
                d[key] = float(value)
            else:
                d[key] = value
        except (ValueError, KeyError):
            kind = ("on/off, true/false or 1/0" if isinstance(current, bool)
                    else f"a valid {type(current).__name__}")
            raise ConfigError(f"--set {key}={value!r}: not {kind}") from None
    return TrainConfig.from_dict(d)


def _main(args: argparse.Namespace) -> int:
    resume = None
    if args.resume is not None:
        if args.set or args.config or args.force:
            raise ConfigError("--resume continues a run with its own settings: drop "
                              "--set/--config/--force")
        if args.out is not None and args.out.resolve() != args.resume.resolve():
            raise ConfigError(f"--resume writes into its run folder {args.resume}: drop --out")
        resume = load_resume(args.resume)
        cfg, out = TrainConfig.from_dict(resume["config"]), args.resume
        data = args.data if args.data is not None else Path(resume["data"])
    else:
        if args.data is None or args.out is None:
            raise ConfigError("give DATA and --out RUN (or --resume RUN)")
        cfg = TrainConfig.from_toml(args.config) if args.config else TrainConfig()
        cfg = parse_sets(args.set, cfg)
        data, out = args.data, args.out
        held = [f for f in RUN_FILES if (out / f).exists()]
        if held and not args.force:
            more = (f", or --resume {out} to continue it" if (out / RESUME).exists()
                    else " (it finished: nothing to resume)")
            raise ConfigError(f"{out}: holds a run already ({held[0]}): choose another --out "
                              f"or add --force to overwrite it{more}")
        if args.force:
            (out / RESUME).unlink(missing_ok=True)
    try:
        m = train(data, out, cfg, progress=not args.quiet,
                  resume=resume["state"] if resume else None)
    except KeyboardInterrupt:  # before the first epoch (loading, EMD features): nothing to keep
        print("tactile-train: interrupted before training started: nothing saved",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    if m.get("interrupted"):
        return EXIT_INTERRUPTED
    if "accuracy" not in m:  # not rank 0 of a torchrun job: rank 0 prints
        return 0
    print(table(m, tuple(m["classes"]), f"test split ({m['split']})"))
    print(f"per take (majority vote): {m['take_accuracy']:.3f} over {m['takes']} takes")
    print(shifted_line(m["shifted"]))
    print(f"trained in {m['train_seconds']} s; run in {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run("tactile-train", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["train", "load_checkpoint", "centered", "parse_sets", "main", "EXIT_INTERRUPTED"]
