"""The training loop: Adam over the features computed once (L-BFGS on all windows at once for
a linear head on pooled features: :func:`full_batch`), early stopping on the validation split,
an optional refit on training + validation windows, Ctrl-C between batches.

:func:`fit` runs the phases; :func:`train_head` one phase, epoch after epoch; each epoch ends
with a :func:`~tactile.training.resume.snapshot` in :attr:`Context.snapshot` (what an
interrupted run saves). Shapes: U training units of S consecutive windows, B units a batch,
T steps, F features, L layers, H hidden.
"""

from __future__ import annotations

import copy
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from torch import nn
from torch.optim.lr_scheduler import ReduceLROnPlateau
from tqdm import tqdm

from tactile.errors import ConfigError
from tactile.training import blend
from tactile.training.config import TrainConfig
from tactile.training.data import Windows, concat
from tactile.training.dist import Dist
from tactile.training.evaluate import predict, runs
from tactile.training.log import Log, Stop
from tactile.training.model import Blend, Classifier, member_loss
from tactile.training.resume import Live, LoopState, restore, snapshot
from tactile.training.sampling import epoch_order


class Interrupted(Exception):
    """Raised inside the loop when a stop was requested; :func:`tactile.training.train.train`
    saves and returns."""


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


@dataclass
class Context:
    """What the training loop needs besides the model and the data."""

    cfg: TrainConfig
    log: Log
    dist: Dist
    device: torch.device
    stop: Stop | None = None
    on_epoch: Callable[[str, int], None] | None = None
    """called after each finished epoch: (phase, epoch), 1-based"""
    snapshot: dict | None = None
    """the state after the last finished epoch"""
    fit_history: dict | None = None
    """the first phase's, once a refit runs"""
    fit_best: dict | None = None
    """the first phase's best weights, during a refit"""
    _unroll: Unroll | None = field(default=None, repr=False)

    def unroll(self, head: nn.Module) -> Unroll:
        """One :class:`Unroll` of ``head`` for the whole run (DDP wraps it once)."""
        if self._unroll is None:
            self._unroll = Unroll(head)
        return self._unroll


class Phase(NamedTuple):
    """What one phase's epochs share: ``step`` the head unrolled over a unit's windows (in
    DDP under torchrun: gradients averaged), ``loss_fn``, ``batch`` units a batch per process,
    ``offset`` (F,) the random offsets' half-widths or None, and the data: ``units`` (U, S)
    window rows, ``f`` (N, T, F) the windows' features, ``y`` (N,) their labels."""

    step: nn.Module
    loss_fn: nn.Module
    batch: int
    offset: torch.Tensor | None
    units: np.ndarray
    f: torch.Tensor
    y: torch.Tensor


def fit(model: Classifier, parts: dict, feats: dict, ctx: Context,
        resume: dict | None = None) -> dict:
    """Train with early stopping on the validation split; with ``refit``, then train the head
    again from a fresh start on the training and validation windows together, for as many
    epochs as the best validation epoch took (the final model has seen the validation data).
    ``resume``: the state saved at an interruption, in either phase."""
    cfg = model.cfg
    if resume is None or resume["phase"] == "fit":
        history = train_head(model, parts["train"], feats["train"], cfg.epochs, ctx,
                             val=(parts["val"], feats["val"]), resume=resume)
    else:
        history = resume["fit_history"]
    blended = isinstance(model.head, Blend)
    if blended and "blend" not in history:  # (a resumed refit has chosen already)
        t0 = time.process_time()
        history["blend"] = b = blend.choose(model, parts, feats, ctx.dist, _stop_check(ctx))
        b["cpu_seconds"] = round(time.process_time() - t0, 1)
        ctx.log.info(f"blended regression: C {b['c']:g}, mix {b['mix']:g}; validation "
                     f"accuracy {b['val_acc']:.3f} ({blend.NAMES[cfg.model]} "
                     f"{b['recurrent_val_acc']:.3f}, regression {b['regression_val_acc']:.3f}; "
                     f"{b['cpu_seconds']:g} s of CPU)")
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
        both = concat(parts["train"], parts["val"])
        f_both = torch.cat([feats["train"], feats["val"]])
        refit = train_head(model, both, f_both, epochs, ctx, resume=resume)
        history["refit_epochs"] = epochs
        if blended:
            t0 = time.process_time()
            blend.refit(model, both, f_both, history["blend"], ctx.dist)
            history["blend"]["refit_cpu_seconds"] = round(time.process_time() - t0, 1)
        # (a full-batch head's refit is an L-BFGS fit of a convex objective: nothing to judge)
        reason = None if full_batch(model, cfg, ctx.dist) else refit_failed(
            history["train_loss"], history["best_epoch"], refit["train_loss"])
        history["refit_kept"] = reason is None
        if reason is not None:  # the validated model is the better one to keep
            model.head.load_state_dict(ctx.fit_best)
            acc = (history["blend"]["val_acc"] if blended
                   else history["val_acc"][history["best_epoch"]])
            ctx.log.warn(f"refit not kept: {reason}; the run's model is the first training's "
                         f"best epoch (validation accuracy {acc:.3f})")
    return history


def _stop_check(ctx: Context) -> Callable[[], None]:
    """A check that raises :class:`Interrupted` when a stop was requested (between the steps
    of work done outside the epochs: the blended regression's fits)."""
    def check() -> None:
        if ctx.stop is not None and ctx.stop.requested():
            raise Interrupted
    return check


def refit_failed(fit_loss: list[float], best_epoch: int, refit_loss: list[float]) -> str | None:
    """Why a refit's model is not kept, or None when it is.

    A refit trains blind (no validation), so its own training loss is the only check: the
    refit must have come at least halfway from where the first training started (its first
    epoch's training loss) to where it stood at its best epoch. A refit that has not (e.g. one
    whose units all died and which predicts the class frequencies for every window) would ship
    a model worse than the validated one. Judged only when the first training lowered its
    loss by at least :data:`REFIT_PROGRESS` of it: the refit's loss is over the training and
    validation windows, the first training's over the training windows alone, and that
    difference must be small beside the progress the check relies on."""
    if not refit_loss or best_epoch < 1 or best_epoch >= len(fit_loss):
        return None
    start, best, last = fit_loss[0], fit_loss[best_epoch], refit_loss[-1]
    if not start - best >= REFIT_PROGRESS * start:  # (NaN too)
        return None
    limit = (start + best) / 2
    if last <= limit:  # (a NaN loss is not)
        return None
    return (f"its training loss after {len(refit_loss)} epochs is {last:.4f}, above "
            f"{limit:.4f}, halfway from the first training's {start:.4f} (epoch 1) to its "
            f"{best:.4f} (best epoch {best_epoch + 1})")


REFIT_PROGRESS = 0.05
"""The fall in training loss, as a fraction of the first epoch's, below which a first
training's progress is too small to judge a refit by (:func:`refit_failed`)."""


def train_head(model: Classifier, w: Windows, f_all: torch.Tensor, n_epochs: int,
               ctx: Context, val: tuple[Windows, torch.Tensor] | None = None,
               resume: dict | None = None) -> dict:
    """Adam (L-BFGS for a :func:`full_batch` head) on the windows ``w`` (features ``f_all``)
    for at most ``n_epochs``. With ``val``: early stopping on its accuracy or loss
    (``select``), and the best epoch's weights are kept;
    without: the last's. Returns the history (see :class:`LoopState`).
    ``resume``: continue from the state saved after an epoch (weights, optimiser, schedule,
    random generators, early-stopping counters, history)."""
    cfg, dist, head = ctx.cfg, ctx.dist, model.head
    full = full_batch(model, cfg, dist)
    # the head unrolled over a unit's windows; under torchrun in DDP (gradients averaged)
    step = None if full else dist.wrap(ctx.unroll(head), ctx.device)
    if full:  # each epoch one L-BFGS step on every training window (lr: its first step)
        opt = torch.optim.LBFGS(head.parameters(), lr=1.0, max_iter=LBFGS_ITERATIONS,
                                history_size=LBFGS_ITERATIONS, line_search_fn="strong_wolfe")
    else:
        opt = torch.optim.Adam(head.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    live = Live(head, opt, scheduler(opt, cfg, n_epochs),
                gen=torch.Generator().manual_seed(cfg.seed),  # the order: alike everywhere
                aug=torch.Generator().manual_seed(cfg.seed + 7919 * dist.rank))  # per process
    # units of training, (U, S) window rows: S consecutive windows whose state is carried
    # (state='carry'), else one window each (S = 1)
    units = sequences(w, cfg.carry_steps) if cfg.state == "carry" else np.arange(len(w))[:, None]
    data = Phase(step, nn.CrossEntropyLoss(label_smoothing=cfg.label_smoothing),
                 math.ceil(cfg.batch_size / dist.world),  # per process: the global batch stays
                 model.offset_scale(), units, f_all, torch.from_numpy(w.y).long())
    phase = "fit" if val is not None else "refit"
    st = LoopState(ema={k: v.detach().clone() for k, v in head.state_dict().items()}
                   if cfg.ema else None)
    if resume is not None:
        st = restore(resume, live)
        ctx.snapshot = resume  # a stop before this phase's next epoch saves the same state
    pooled = None
    if full:  # the features pooled once; the standardisation fixed to the training windows'
        pooled = head.pooled(f_all[units[:, 0]].to(ctx.device))
        head.set_norm(pooled)
    history = st.history
    # a resumed phase that had stopped early is over (it was interrupted after its last epoch)
    last = st.epoch if val is not None and st.stale >= cfg.patience else n_epochs
    epochs = tqdm(range(st.epoch, last), desc=phase, disable=not ctx.log.bars,
                  file=sys.stderr, initial=st.epoch, total=n_epochs)
    for epoch in epochs:
        t_epoch = time.perf_counter()
        history["train_loss"].append(_full_batch_epoch(live, data, pooled, ctx) if full
                                     else _epoch(model, live, st, data, ctx, epoch))
        line = f"{phase} epoch {epoch + 1}/{n_epochs}: train loss {history['train_loss'][-1]:.3f}"
        stop = False
        if val is None:  # (a plateau schedule needs a validation loss: the rate stays)
            _step_schedule(live.sched, None)
        else:
            val_loss, val_acc = validate(model, val, st, epoch, dist)
            epochs.set_postfix(loss=f"{history['train_loss'][-1]:.3f}",
                               val_loss=f"{val_loss:.3f}", val_acc=f"{val_acc:.3f}")
            _step_schedule(live.sched, val_loss)
            stop = st.stale >= cfg.patience
            line += (f", val loss {val_loss:.3f}, val acc {val_acc:.3f}"
                     f"{' (best)' if st.stale == 0 else ''}")
        st.epoch = epoch + 1
        if not ctx.log.bars:  # a log file or CI: one plain line per epoch
            ctx.log.info(f"{line} ({time.perf_counter() - t_epoch:.1f} s)")
        ctx.snapshot = snapshot(phase, st, live, ctx.fit_history, ctx.fit_best)
        if ctx.on_epoch is not None:
            ctx.on_epoch(phase, epoch + 1)
        if stop:
            ctx.log.info(f"early stop after epoch {epoch + 1}: best epoch "
                         f"{history['best_epoch'] + 1}")
            break
    if val is not None:
        head.load_state_dict(st.best_state)
    elif st.ema is not None:
        head.load_state_dict(st.ema)
    return history


LBFGS_ITERATIONS = 20
"""L-BFGS iterations an epoch of a full-batch fit (:func:`full_batch`)."""


def full_batch(model: Classifier, cfg: TrainConfig, dist: Dist) -> bool:
    """Whether the head is fitted on all training windows at once: a head marked
    ``full_batch`` (the granular ``linear`` model: a linear map of features pooled over the
    window), one process, and nothing that makes an epoch's data random
    (gain or offset augmentation, a running average of the weights). Its objective is
    convex, so L-BFGS reaches the optimum mini-batch Adam only approaches: the training loss
    of cross-entropy plus weight decay (``weight_decay / 2`` times the squared weights, the
    penalty Adam's ``weight_decay`` adds), with the batch normalisation fixed to the training
    windows' statistics. Anything else trains with Adam on mini-batches."""
    return (getattr(model.head, "full_batch", False) and dist.world == 1
            and not cfg.augment_gain and model.offset_scale() is None and not cfg.ema)


def _full_batch_epoch(live: Live, data: Phase, pooled: torch.Tensor, ctx: Context) -> float:
    """One L-BFGS step (at most :data:`LBFGS_ITERATIONS` iterations) on the pooled features
    (N, F) of every training window; returns the training loss (cross-entropy) after it.
    Raises :class:`Interrupted` when a stop is requested."""
    if ctx.stop is not None and ctx.stop.requested():
        raise Interrupted
    head, y = live.head, data.y.to(pooled.device)
    head.train()
    head.norm.eval()  # the statistics set_norm fixed, as evaluation uses them
    decay = ctx.cfg.weight_decay

    def objective() -> torch.Tensor:
        live.opt.zero_grad()
        loss = data.loss_fn(head.classify(pooled), y)
        loss = loss + 0.5 * decay * sum(p.pow(2).sum() for p in head.parameters())
        loss.backward()
        return loss

    live.opt.step(objective)
    with torch.no_grad():
        return float(data.loss_fn(head.classify(pooled), y))


def _epoch(model: Classifier, live: Live, st: LoopState, data: Phase, ctx: Context,
           epoch: int) -> float:
    """One epoch's batches (each process its shard of the epoch's units); returns the mean
    training loss over every process's windows. Raises :class:`Interrupted` when a stop is
    requested."""
    cfg, dist, dev, head = ctx.cfg, ctx.dist, ctx.device, live.head
    model.train()
    order = dist.shard(epoch_order(data.units, cfg.epoch_windows, live.gen))
    total, count = 0.0, 0
    for i in tqdm(range(0, len(order), data.batch), desc=f"epoch {epoch + 1}",
                  disable=not ctx.log.bars, leave=False, file=sys.stderr):
        if ctx.stop is not None and ctx.stop.requested():
            raise Interrupted
        rows = order[i : i + data.batch]  # (B, S)
        f = data.f[rows].to(dev)  # (B, S, T, F)
        if cfg.augment_gain:  # random gains per window: the model's augment_gain
            f = model.augment_gain(f, cfg.augment_gain, live.aug)
        if data.offset is not None:  # then random offsets per window on the uncentred channels
            f = augment_offset(f, data.offset, live.aug)
        h, c = (t.to(dev) for t in model.zero_state(len(rows)))
        # (B, S, classes), an ensemble's (B, S, members, classes): every window's loss
        logits = data.step(f, h, c)
        loss = member_loss(data.loss_fn, logits, data.y[rows].to(dev))
        live.opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(head.parameters(), 5.0)
        live.opt.step()
        if st.ema is not None:
            with torch.no_grad():
                for k, v in head.state_dict().items():
                    if v.is_floating_point():  # not a step counter (batch norm's)
                        st.ema[k].mul_(cfg.ema).add_(v, alpha=1 - cfg.ema)
        total += float(loss.detach()) / cfg.ensemble * len(rows)  # members' mean
        count += len(rows)
    total, count = dist.sum(total, count)
    return total / count


def augment_offset(f: torch.Tensor, offset: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """A batch's features (B, S, T, F) plus, per window and feature, a random offset uniform in
    ``+/- offset`` ((F,) half-widths, the model's ``offset_scale``), constant over the
    window's T steps. Drawn from ``gen`` on the CPU after the gains (without offsets the draws
    are those of earlier versions)."""
    shape = (*f.shape[:2], 1, f.shape[-1])  # (B, S, 1, F)
    return f + (offset * (2 * torch.rand(shape, generator=gen) - 1)).to(f.device)


def validate(model: Classifier, val: tuple[Windows, torch.Tensor], st: LoopState, epoch: int,
             dist: Dist) -> tuple[float, float]:
    """One epoch's validation: the loss and accuracy (of the averaged weights with ``ema``),
    appended to ``st.history``; the best epoch's weights and counters kept in ``st``. Returns
    (loss, accuracy in [0, 1]). Under torchrun every process validates rank 0's model and
    takes rank 0's figures, so that all of them keep the same best epoch and stop together."""
    head, cfg, history = model.head, model.cfg, st.history
    dist.sync_buffers(head)
    if st.ema is not None:  # validate (and keep) the averaged weights
        live = {k: v.clone() for k, v in head.state_dict().items()}
        head.load_state_dict(st.ema)
    probs = predict(model, val[0], feats=val[1])
    val_loss_fn = nn.CrossEntropyLoss()  # unsmoothed: early stopping compares true fits
    val_loss = float(val_loss_fn(torch.log(torch.from_numpy(probs) + 1e-9),
                                 torch.from_numpy(val[0].y).long()))
    val_acc = float((probs.argmax(1) == val[0].y).mean())
    val_loss, val_acc = (float(v) for v in dist.broadcast(np.array([val_loss, val_acc]))[0])
    history["val_loss"].append(val_loss)
    history["val_acc"].append(val_acc)
    if improves(cfg.select, val_acc, val_loss, st.best, st.best_acc):
        st.best, st.best_acc, st.stale = val_loss, val_acc, 0
        history["best_epoch"] = epoch
        st.best_state = {k: v.clone() for k, v in head.state_dict().items()}
    else:
        st.stale += 1
    if st.ema is not None:
        head.load_state_dict(live)
    return val_loss, val_acc


def improves(select: str, val_acc: float, val_loss: float, best_loss: float,
             best_acc: float) -> bool:
    """Whether this epoch beats the best so far (``best_loss``, ``best_acc``: its validation
    figures): ``loss``, a validation loss lower by more than 1e-4; ``accuracy``, a higher
    validation accuracy, or the same with such a lower loss."""
    lower = val_loss < best_loss - 1e-4
    if select == "loss":
        return lower
    return val_acc > best_acc + 1e-9 or (abs(val_acc - best_acc) <= 1e-9 and lower)


def scheduler(opt: torch.optim.Optimizer, cfg: TrainConfig, n_epochs: int):
    """The learning-rate schedule of ``cfg.schedule`` (None: constant ``lr``)."""
    if cfg.schedule == "plateau":  # halve the rate when validation loss stalls
        return ReduceLROnPlateau(
            opt, factor=0.5, patience=max(1, cfg.patience // 4))
    if cfg.schedule == "cosine":  # from lr down to lr / 100 over the epochs
        return torch.optim.lr_scheduler.CosineAnnealingLR(opt, n_epochs, eta_min=cfg.lr / 100)
    return None


def _step_schedule(sched, val_loss: float | None) -> None:
    """The schedule's step after an epoch; a plateau schedule steps on the validation loss,
    so without one (a refit) its rate stays."""
    if isinstance(sched, ReduceLROnPlateau):
        if val_loss is not None:
            sched.step(val_loss)
    elif sched is not None:
        sched.step()


def sequences(w: Windows, steps: int) -> np.ndarray:
    """(U, steps) row indices of consecutive windows within one run (carried-state training)."""
    seqs = []
    for rows in runs(w):
        for i in range(0, len(rows) - steps + 1, steps):
            seqs.append(rows[i : i + steps])
    if not seqs:
        raise ConfigError(f"no run holds {steps} consecutive windows: lower carry_steps")
    return np.stack(seqs)


__all__ = ["Context", "Interrupted", "Unroll", "fit", "train_head", "validate", "improves",
           "augment_offset", "scheduler", "sequences"]
