"""Train a classifier on a dataset folder and write an evaluated run: tactile-train DATA --out RUN.

Reads top to bottom: load takes -> split by user/take/time -> cut windows -> normalisation from
the training windows -> features (EMD once, up front) (:mod:`~tactile.training.prepare`) ->
train with Adam and early stopping on the validation split (:mod:`~tactile.training.loop`) ->
evaluate on the test split -> write RUN/ (:mod:`~tactile.training.run_files`):

    checkpoint.pt     weights + resolved config + classes, channels, rate, normalisation,
                      test rows and metrics (torch.load(weights_only=True) reads it)
    metrics.json      the figures; confusion.txt the paper-style table;
    curves.png, confusion.png
    resume.pt         only after Ctrl-C or SIGTERM: the state to continue from (--resume RUN)

Under ``torchrun`` the same command trains data-parallel (:mod:`tactile.training.dist`): every
process takes its share of each epoch's windows, rank 0 alone prints and writes RUN/.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from tactile.device.recordings import load_dataset
from tactile.errors import ConfigError, OutputError, RecordingError
from tactile.training import blend
from tactile.training.checkpoint import (  # load_checkpoint: export reads runs through here
    CHECKPOINT,
    RESUME,
    load_checkpoint,
    save_resume,
)
from tactile.training.config import (
    TrainConfig,
    apply_threads,
    resolve_device,
    resolve_threads,
    usable_cpus,
)
from tactile.training.data import name_list
from tactile.training.dist import Dist
from tactile.training.log import Log, Stop
from tactile.training.loop import Context, Interrupted, fit
from tactile.training.model import Classifier
from tactile.training.models import build_model
from tactile.training.prepare import Prepared, check_inputs, features, prepare
from tactile.training.run_files import held_out_streams, run_metrics, write_run


def train(data: Path, out: Path, cfg: TrainConfig, progress: bool = True, *,
          resume: dict | None = None,
          on_epoch: Callable[[str, int], None] | None = None) -> dict:
    """Train, evaluate and save a run; returns the metrics (``interrupted`` True when SIGINT,
    or SIGTERM in a training of one process, stopped it: RUN/ then holds the best checkpoint so
    far and ``resume.pt``, and ``stopped_by`` names the signal).

    ``resume``: the state :func:`~tactile.training.checkpoint.load_resume` read, to continue an
    interrupted run (``cfg`` must be its config). ``on_epoch(phase, epoch)``: called after each
    finished epoch (1-based; phase ``fit`` or ``refit``), after its state is saved in memory."""
    t_start, cpu_start = time.perf_counter(), time.process_time()
    dist = Dist.from_env()
    log = Log(progress, dist.is_main)
    threads = apply_threads(resolve_threads(cfg.threads, dist.local_world))
    device = dist.device(resolve_device(cfg.device))
    dist.start(device)
    _seed(cfg.seed)
    takes = load_dataset(data)
    if resume is not None:
        same_takes(data, takes, resume.get("takes"))
    classes, channels = check_inputs(data, takes, cfg)
    if cfg.blends:
        blend.check_available(cfg.blend)  # its solver, before the training it follows
    # said once the data is known to fit: a bad input's error is then the only line
    job = f"; {dist.world} processes in all (rank 0 writes)" if dist.world > 1 else ""
    cpus = usable_cpus()
    log.info(f"threads {threads} per process ({'set' if cfg.threads else 'automatic'}; "
             f"{cpus} usable CPUs, {dist.local_world} process(es) here); device "
             f"{device}{job}")
    if threads * dist.local_world > cpus:  # a set count, or more processes than CPUs
        log.warn(f"{threads} thread(s) x {dist.local_world} process(es) here is more than the "
                 f"{cpus} usable CPUs: the threads share them and training runs several "
                 "times slower (docs/training.md, 'Machine')")
    prep = prepare(takes, classes, channels, cfg, log, dist)
    cfg, norm = prep.cfg, prep.norm
    model = build_model(cfg, len(classes), torch.from_numpy(norm.mean),
                        torch.from_numpy(norm.std), channels=channels,
                        rate_hz=takes[0].info.sample_rate_hz, emd_index=norm.emd_index,
                        center_index=norm.center_index)
    if resume is not None and "prep_version" not in resume and (
            prep.split.by_class or getattr(model.pre, "center_groups", None)):
        raise RecordingError(
            f"{data}: this run was saved before takes of one class each were drawn class by "
            "class and a high-rate signal was centred whole: it cannot go on as it started; "
            "train it again")
    t0 = time.perf_counter()
    feats = features(model, prep.parts, cfg.seed, log, dist)
    model.fit_features(feats["train"])  # what the head keeps of them (an F-RNN's input scale)
    feature_s = time.perf_counter() - t0
    model.to(device)
    ctx = Context(cfg, log, dist, device, None, on_epoch)
    # Ctrl-C (SIGTERM) stops at the next batch or blend fit; after the last epoch (and the
    # blend's choice) it is only noted (the run is saved)
    with Stop(dist) as ctx.stop:
        try:
            history = fit(model, prep.parts, feats, ctx, resume)
        except Interrupted:
            model.to("cpu")
            saved = (_save_interrupted(out, data, model, ctx, prep, feats) if dist.is_main
                     else {"interrupted": True})
            saved = {**saved, "stopped_by": ctx.stop.signal or "SIGINT"}  # not in the files
            dist.barrier()  # the others wait for rank 0's files: torchrun ends a failed job
            dist.finish()
            return saved
        model.to("cpu")
        dist.finish()
        if not dist.is_main:
            return {"interrupted": False}
        metrics = run_metrics(model, prep, feats["test"], history, dict(
            refit_epochs=history.get("refit_epochs", 0),
            refit_kept=history.get("refit_kept"),
            epochs_run=len(history["train_loss"]),
            centered=[channels[i] for i in norm.center_index],
            feature_seconds=round(feature_s, 1),
            train_seconds=round(time.perf_counter() - t_start, 1),
            train_cpu_seconds=round(time.process_time() - cpu_start, 1),
            threads=threads, device=str(device), processes=dist.world, seed=cfg.seed,
            interrupted=False,
        ), robustness=True)
        held = held_out_streams(model, ctx.fit_best, prep) if history.get("refit_kept") else None
        write_run(out, cfg, model, metrics, history, prep, held)
        (out / RESUME).unlink(missing_ok=True)  # finished: nothing left to resume
    return metrics


def _save_interrupted(out: Path, data: Path, model: Classifier, ctx: Context, prep: Prepared,
                      feats: dict) -> dict:
    """After SIGINT (SIGTERM): RUN/resume.pt (the state after the last finished epoch), and the best
    weights so far as an ordinary run (checkpoint, test metrics marked ``interrupted``)."""
    snap = ctx.snapshot
    if snap is None:
        ctx.log.warn(f"interrupted ({ctx.stop.signal or 'SIGINT'}) before the first epoch "
                     "ended: nothing to save")
        return {"interrupted": True, "epochs_run": 0}
    out.mkdir(parents=True, exist_ok=True)
    # the takes by content: a resume on another dataset (same names, other recordings) would
    # draw another split and mix two datasets in one run
    snap = {**snap, "takes": {t.path.name: t.fingerprint() for t in prep.takes}}
    save_resume(out, prep.cfg, data, ctx.dist.world, snap)
    if snap["phase"] == "fit":
        best, history = snap["best_state"] or snap["head"], snap["history"]
    else:  # a refit stopped half-way: the first phase's best model is the best there is
        best, history = snap["fit_best"], snap["fit_history"]
    model.head.load_state_dict(best)
    metrics = run_metrics(model, prep, feats["test"], history, dict(
        epochs_run=len(history["train_loss"]), phase=snap["phase"], interrupted=True,
        shifted=None, seed=prep.cfg.seed,
    ), robustness=False)
    try:
        write_run(out, prep.cfg, model, metrics, history, prep)
    except (OutputError, ConfigError) as e:  # the state to go on from is saved all the same
        raise type(e)(f"{e}, but {RESUME} is (the state after {snap['phase']} epoch "
                      f"{snap['epoch']}): make room, then tactile-train --resume {out}") from None
    ctx.log.warn(f"interrupted ({ctx.stop.signal or 'SIGINT'}): {snap['phase']} epoch "
                 f"{snap['epoch']} was the last finished; "
                 f"best checkpoint so far in {out / CHECKPOINT}; continue with "
                 f"tactile-train --resume {out}")
    return metrics


def same_takes(data: Path, takes: list, saved: object) -> None:
    """A resumed run reads the takes it started on: ``saved`` ({file name: fingerprint}, from
    its resume state; absent in a state saved before it was kept: not checked) against
    ``takes`` of ``data``, else a one-line :class:`RecordingError`."""
    if not isinstance(saved, dict):
        return
    now = {t.path.name: t.fingerprint() for t in takes}
    if now == saved:
        return
    missing = sorted(set(saved) - set(now))
    added = sorted(set(now) - set(saved))
    other = sorted(n for n in set(now) & set(saved) if now[n] != saved[n])
    said = [f"{what} {name_list(names, 3)}" for what, names in (
        ("other recordings in", other), ("missing", missing), ("new", added)) if names]
    raise RecordingError(f"{data}: not the takes this run started on ({'; '.join(said)}): "
                         "give the dataset it was started on")


def _seed(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


__all__ = ["train", "load_checkpoint"]
