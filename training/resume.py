"""The state of training after an epoch, and putting it back: what ``resume.pt`` holds.

:class:`LoopState` is where a phase (``fit`` or ``refit``) stands; :func:`snapshot` copies it
with the weights, optimiser, schedule and random generators (:class:`Live`) into plain tensors,
numbers and lists (``torch.load(weights_only=True)`` reads them: see
:func:`tactile.training.checkpoint.save_resume`); :func:`restore` puts such a copy back.
"""

from __future__ import annotations

import copy
import math
import random
from dataclasses import dataclass, field, fields

import numpy as np
import torch
from torch import nn

from tactile.errors import RecordingError
from tactile.training.checkpoint import OLD_F_RNN, RESUME, old_f_rnn

AUGMENT_VERSION = 2
PREP_VERSION = 2
"""2: takes of one class each drawn class by class into the parts, a high-rate signal centred
whole (a state without the key was saved before: neither)."""
"""The gain augmentation a resume state was saved with: 2 draws one gain per window and
modality for granular models (before, per window and feature; the pen's is unchanged)."""


def _history() -> dict:
    return {"train_loss": [], "val_loss": [], "val_acc": [], "best_epoch": 0}


@dataclass
class LoopState:
    """Where one phase of training stands after its last finished epoch."""

    epoch: int = 0
    """epochs finished in this phase"""
    best: float = math.inf
    """the validation loss of the best epoch so far (the one whose weights are kept)"""
    best_acc: float = -1.0
    """that epoch's validation accuracy, in [0, 1] (-1: none yet)"""
    best_state: dict | None = None
    """that epoch's weights (a state dict; None before the first validation)"""
    stale: int = 0
    """epochs since the best one (early stopping at ``patience``)"""
    history: dict = field(default_factory=_history)
    """per epoch: ``train_loss``, ``val_loss``, ``val_acc`` (lists), and ``best_epoch`` (0-based)"""
    ema: dict | None = None
    """the exponential moving average of the weights, updated every step (None: ``ema`` off)"""

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class Live:
    """What an epoch changes besides :class:`LoopState`: the head's weights, the optimiser,
    the schedule (None: a constant rate), the generators of the epoch's order (``gen``, alike
    on every process) and of the augmentation (``aug``, one per process)."""

    head: nn.Module
    opt: torch.optim.Optimizer
    sched: object | None
    gen: torch.Generator
    aug: torch.Generator


def rng_state(gen: torch.Generator, aug: torch.Generator) -> dict:
    """Every random generator's state (torch, numpy, Python, CUDA, ``gen``, ``aug``), as
    plain tensors and lists."""
    name, keys, pos, has_gauss, gauss = np.random.get_state()
    version, internal, py_gauss = random.getstate()
    state = {"torch": torch.get_rng_state(), "order": gen.get_state(), "gain": aug.get_state(),
             "numpy": [name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss),
                       float(gauss)],
             "python": [version, list(internal), py_gauss]}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict, gen: torch.Generator, aug: torch.Generator) -> None:
    """Put back what :func:`rng_state` saved."""
    torch.set_rng_state(state["torch"])
    gen.set_state(state["order"])
    aug.set_state(state["gain"])
    name, keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
    version, internal, py_gauss = state["python"]
    random.setstate((version, tuple(internal), py_gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def snapshot(phase: str, state: LoopState, live: Live, fit_history: dict | None,
             fit_best: dict | None) -> dict:
    """Everything an epoch boundary knows, copied (training goes on changing the live ones).
    ``fit_history``, ``fit_best``: the first phase's history and best weights, during a
    refit."""
    return copy.deepcopy({
        "phase": phase, **state.to_dict(), "head": live.head.state_dict(),
        "opt": live.opt.state_dict(), "optimizer": type(live.opt).__name__,
        "sched": live.sched.state_dict() if live.sched is not None else None,
        "rng": rng_state(live.gen, live.aug), "fit_history": fit_history, "fit_best": fit_best,
        "augment_version": AUGMENT_VERSION, "prep_version": PREP_VERSION,
    })


def restore(saved: dict, live: Live) -> LoopState:
    """Put a :func:`snapshot` back into ``live``; returns its loop state. A state that does not
    fit (edited, or from another version) is a RecordingError, not a traceback."""
    kind = saved.get("optimizer", "Adam")  # states saved before the key: Adam's
    if kind != type(live.opt).__name__:
        raise RecordingError(f"{RESUME}: saved by a version that trained this model with {kind}, "
                             f"this one trains it with {type(live.opt).__name__}: train it again")
    try:
        live.head.load_state_dict(saved["head"])
        live.opt.load_state_dict(saved["opt"])
        if live.sched is not None:
            live.sched.load_state_dict(saved["sched"])
        set_rng_state(saved["rng"], live.gen, live.aug)
        kept = {k: copy.deepcopy(saved[k]) for k in ("epoch", "best", "best_state", "stale",
                                                     "history", "ema")}
        history, epoch, stale = kept["history"], kept["epoch"], kept["stale"]
        if not (isinstance(history, dict) and set(_history()) <= set(history)
                and all(isinstance(history[k], list) for k in _history() if k != "best_epoch")
                and isinstance(epoch, int) and epoch >= 1 and isinstance(stale, int)
                and stale >= 0):  # an edit the loop would meet only later, as a traceback
            raise ValueError(f"epoch {epoch!r}, stale {stale!r} and the history must be what "
                             "an epoch's end saves")
        # best_acc is absent from older resume files
        return LoopState(**kept, best_acc=float(saved.get("best_acc", -1.0)))
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as e:
        if old_f_rnn(saved.get("head")):
            raise RecordingError(f"{RESUME}: {OLD_F_RNN}") from None
        first = " ".join(str(e).split())[:120]
        raise RecordingError(f"{RESUME}: the saved state does not fit this run "
                             f"({type(e).__name__}: {first})") from None


__all__ = ["AUGMENT_VERSION", "PREP_VERSION", "LoopState", "Live", "snapshot", "restore",
           "rng_state", "set_rng_state"]
