"""``tactile-train DATA --out RUN/``: recordings in, an evaluated checkpoint out.

Reads top to bottom: load takes -> split by user/take/time -> cut windows -> normalisation from
the training windows -> features (EMD once, up front) -> train with Adam and early stopping on
the validation split -> evaluate on the test split -> write RUN/:

    checkpoint.pt     weights + resolved config + classes, channels, rate, normalisation,
                      test rows and metrics (torch.load(weights_only=True) reads it)
    metrics.json      the figures; confusion.txt the paper-style table;
    curves.png, confusion.png
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.optim.lr_scheduler import ReduceLROnPlateau
from tqdm import tqdm

import tactile
from tactile.cli import Parser, add_debug, run
from tactile.device.recording import load_dataset
from tactile.errors import ConfigError, RecordingError
from tactile.training.config import TrainConfig
from tactile.training.data import (
    Windows,
    channel_index,
    channel_stats,
    classes_of,
    concat,
    cut,
    split_takes,
)
from tactile.training.evaluate import _runs, predict, shifted, summary, table
from tactile.training.model import TextureModel
from tactile.training.sampling import epoch_order

CHECKPOINT = "checkpoint.pt"
CHECKPOINT_FORMAT = "tactile-checkpoint"
CHECKPOINT_VERSION = 1


def train(data: Path, out: Path, cfg: TrainConfig, progress: bool = True) -> dict:
    """Train, evaluate and save a run; returns the metrics."""
    t_start = time.perf_counter()
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    takes = load_dataset(data)
    classes = classes_of(takes)
    if len(classes) < 2:
        raise RecordingError(f"{data}: only one label ({classes[0]}); need at least two classes")
    channels = tuple(takes[0].channels[i] for i in channel_index(takes[0], cfg.channels))
    missing = [c for c in cfg.emd_channels if c not in channels]
    if missing:
        raise ConfigError(f"emd_channels {missing} not among the input channels {list(channels)}")
    cfg = cfg.replace(channels=channels)
    split = split_takes(takes, cfg)
    parts = {
        name: cut(takes, classes, channels, cfg.window, cfg.hop, rows)
        for name, rows in (("train", split.train), ("val", split.val), ("test", split.test))
    }
    _log(progress, f"classes {list(classes)}; windows train {len(parts['train'])}, "
         f"val {len(parts['val'])}, test {len(parts['test'])}; split {split.description}")
    mean, std = channel_stats(parts["train"])
    emd_index = [channels.index(c) for c in cfg.emd_channels]
    center_index = centered(channels, cfg.center)
    model = TextureModel(cfg, len(classes), torch.from_numpy(mean), torch.from_numpy(std),
                         emd_index, center_index)
    t0 = time.perf_counter()
    feats = {k: _features(model, w, progress, k) for k, w in parts.items()}
    feature_s = time.perf_counter() - t0
    history = _fit(model, parts, feats, progress)
    test_probs = predict(model, parts["test"])
    metrics = summary(parts["test"].y, test_probs, classes)
    rate = takes[0].info.sample_rate_hz
    metrics["shifted"] = shifted(model, takes, classes, channels, split.test, cfg.window,
                                 cfg.hop, rate)
    metrics.update(
        classes=list(classes), channels=list(channels), split=split.description,
        split_windows={k: len(w) for k, w in parts.items()}, best_epoch=history["best_epoch"],
        val_accuracy=history["val_acc"][history["best_epoch"]],
        refit_epochs=history.get("refit_epochs", 0),
        feature_seconds=round(feature_s, 1),
        train_seconds=round(time.perf_counter() - t_start, 1),
        threads=cfg.threads, seed=cfg.seed,
    )
    out.mkdir(parents=True, exist_ok=True)
    names = [t.path.name for t in takes]
    ck = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "package_version": tactile.__version__,
        "config": cfg.to_dict(),
        "classes": list(classes),
        "channels": list(channels),
        "units": [takes[0].info.channels[takes[0].channels.index(c)].unit for c in channels],
        "sample_rate_hz": rate,
        "mean": mean.tolist(),
        "std": std.tolist(),
        "emd_index": emd_index,
        "center_index": center_index,
        "test_rows": {names[i]: list(r) for i, r in split.test.items()},
        "metrics": _plain(metrics),
        "state_dict": model.state_dict(),
    }
    torch.save(ck, out / CHECKPOINT)
    (out / "metrics.json").write_text(json.dumps(_plain(metrics), indent=1) + "\n")
    (out / "confusion.txt").write_text(table(metrics, classes, "test split") + "\n")
    _plots(out, history, metrics, classes)
    return metrics


def centered(channels: tuple[str, ...], patterns: tuple[str, ...]) -> list[int]:
    """Indices of the channels matching any ``center`` pattern (shell-style, e.g. ``accel_*``)."""
    return [i for i, c in enumerate(channels) if any(fnmatch.fnmatchcase(c, p) for p in patterns)]


def _features(model: TextureModel, w: Windows, progress: bool, name: str) -> torch.Tensor:
    """(N, T, F) features of every window, computed once (they have no trainable part)."""
    x = torch.from_numpy(w.x)
    chunks = []
    with torch.no_grad():
        for i in tqdm(range(0, len(x), 512), desc=f"features {name}", disable=not progress,
                      leave=False, file=sys.stderr):
            chunks.append(model.pre(x[i : i + 512]))
    return torch.cat(chunks)


def _sequences(w: Windows, steps: int) -> np.ndarray:
    """(S, steps) row indices of consecutive windows within one run (carried-state training)."""
    seqs = []
    for rows in _runs(w):
        for i in range(0, len(rows) - steps + 1, steps):
            seqs.append(rows[i : i + steps])
    if not seqs:
        raise ConfigError(f"no run holds {steps} consecutive windows: lower carry_steps")
    return np.stack(seqs)


def _fit(model: TextureModel, parts: dict, feats: dict, progress: bool) -> dict:
    """Train with early stopping on the validation split; with ``refit``, then train the head
    again from a fresh start on the training and validation windows together, for as many
    epochs as the best validation epoch took (the final model has seen the validation data)."""
    cfg = model.cfg
    history = _train(model, parts["train"], feats["train"], cfg.epochs, progress,
                     val=(parts["val"], feats["val"]))
    if cfg.refits:
        epochs = history["best_epoch"] + 1
        _log(progress, f"refit on training + validation windows for {epochs} epochs")
        torch.manual_seed(cfg.seed)
        for m in model.head.modules():
            if m is not model.head and hasattr(m, "reset_parameters"):
                m.reset_parameters()
        _train(model, concat(parts["train"], parts["val"]),
               torch.cat([feats["train"], feats["val"]]), epochs, progress)
        history["refit_epochs"] = epochs
    return history


def _train(model: TextureModel, w: Windows, f_all: torch.Tensor, n_epochs: int, progress: bool,
           val: tuple[Windows, torch.Tensor] | None = None) -> dict:
    """Adam on the windows ``w`` (features ``f_all``) for at most ``n_epochs``. With ``val``:
    early stopping on its loss, and the best epoch's weights are kept; without: the last's."""
    cfg = model.cfg
    head = model.head
    opt = torch.optim.Adam(head.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = _scheduler(opt, cfg, n_epochs)
    loss_fn = nn.CrossEntropyLoss(label_smoothing=cfg.label_smoothing)
    val_loss_fn = nn.CrossEntropyLoss()  # unsmoothed: early stopping compares true fits
    y_train = torch.from_numpy(w.y).long()
    carry = cfg.state == "carry"
    units = _sequences(w, cfg.carry_steps) if carry else np.arange(len(w))
    gen = torch.Generator().manual_seed(cfg.seed)
    history = {"train_loss": [], "val_loss": [], "val_acc": [], "best_epoch": 0}
    best, best_state, stale = math.inf, None, 0
    # exponential moving average of the weights, updated every step (None: off)
    ema = {k: v.detach().clone() for k, v in head.state_dict().items()} if cfg.ema else None
    epochs = tqdm(range(n_epochs), desc="epochs", disable=not progress, file=sys.stderr)
    for epoch in epochs:
        model.train()
        order = epoch_order(units, cfg.epoch_windows, gen)
        total, count = 0.0, 0
        for i in tqdm(range(0, len(order), cfg.batch_size), desc=f"epoch {epoch + 1}",
                      disable=not progress, leave=False, file=sys.stderr):
            rows = order[i : i + cfg.batch_size]
            h, c = model.zero_state(len(rows))
            if cfg.augment_gain:  # a random gain per window and feature (B, 1, F)
                shape = (*rows.shape, 1, f_all.shape[-1])
                gain = 1 + cfg.augment_gain * (2 * torch.rand(shape, generator=gen) - 1)
            if carry:  # (B, steps): state flows through the steps, loss at every window
                loss = 0.0
                for s in range(rows.shape[1]):
                    f = f_all[rows[:, s]]
                    if cfg.augment_gain:
                        f = f * gain[:, s]
                    logits, h, c = head(f, h, c)
                    loss = loss + loss_fn(logits, y_train[rows[:, s]])
                loss = loss / rows.shape[1]
            else:
                f = f_all[rows] * gain if cfg.augment_gain else f_all[rows]
                logits, _, _ = head(f, h, c)
                loss = loss_fn(logits, y_train[rows])
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(head.parameters(), 5.0)
            opt.step()
            if ema is not None:
                with torch.no_grad():
                    for k, v in head.state_dict().items():
                        if v.is_floating_point():  # not a step counter (batch norm's)
                            ema[k].mul_(cfg.ema).add_(v, alpha=1 - cfg.ema)
            total += float(loss.detach()) * len(rows)
            count += len(rows)
        history["train_loss"].append(total / count)
        if val is None:  # (a plateau schedule needs a validation loss: the rate stays)
            if sched is not None and not isinstance(sched, ReduceLROnPlateau):
                sched.step()
            continue
        if ema is not None:  # validate (and keep) the averaged weights
            live = {k: v.clone() for k, v in head.state_dict().items()}
            head.load_state_dict(ema)
        probs = predict(model, val[0], feats=val[1])
        val_loss = float(val_loss_fn(torch.log(torch.from_numpy(probs) + 1e-9),
                                     torch.from_numpy(val[0].y).long()))
        val_acc = float((probs.argmax(1) == val[0].y).mean())
        history["val_loss"].append(val_loss)
        history["val_acc"].append(val_acc)
        epochs.set_postfix(loss=f"{total / count:.3f}", val_loss=f"{val_loss:.3f}",
                           val_acc=f"{val_acc:.3f}")
        if isinstance(sched, ReduceLROnPlateau):
            sched.step(val_loss)
        elif sched is not None:
            sched.step()
        if val_loss < best - 1e-4:
            best, stale, history["best_epoch"] = val_loss, 0, epoch
            best_state = {k: v.clone() for k, v in head.state_dict().items()}
        else:
            stale += 1
        if ema is not None:
            head.load_state_dict(live)
        if stale >= cfg.patience:
            _log(progress, f"early stop after epoch {epoch + 1}: best epoch "
                 f"{history['best_epoch'] + 1}")
            break
    if val is not None:
        head.load_state_dict(best_state)
    elif ema is not None:
        head.load_state_dict(ema)
    return history


def _scheduler(opt: torch.optim.Optimizer, cfg: TrainConfig, n_epochs: int):
    """The learning-rate schedule of ``cfg.schedule`` (None: constant ``lr``)."""
    if cfg.schedule == "plateau":  # halve the rate when validation loss stalls
        return ReduceLROnPlateau(
            opt, factor=0.5, patience=max(1, cfg.patience // 4))
    if cfg.schedule == "cosine":  # from lr down to lr / 100 over the epochs
        return torch.optim.lr_scheduler.CosineAnnealingLR(opt, n_epochs, eta_min=cfg.lr / 100)
    return None


def load_checkpoint(run_dir: Path) -> tuple[TextureModel, dict]:
    """Rebuild the model of a run from its checkpoint (data only: weights_only=True)."""
    path = Path(run_dir)
    path = path / CHECKPOINT if path.is_dir() else path
    if not path.is_file():
        raise RecordingError(f"{path}: no checkpoint (train a run with tactile-train first)")
    try:
        ck = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as e:  # noqa: BLE001  (any unpickling failure means "not a checkpoint")
        raise RecordingError(f"{path}: not a readable checkpoint ({e})") from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise RecordingError(f"{path}: not a tactile checkpoint")
    if ck.get("version") != CHECKPOINT_VERSION:
        raise RecordingError(f"{path}: checkpoint version {ck.get('version')}, "
                             f"this package reads {CHECKPOINT_VERSION}")
    cfg = TrainConfig.from_dict({"front": "none", **ck["config"]})  # before fronts: none
    model = TextureModel(cfg, len(ck["classes"]), torch.tensor(ck["mean"]),
                         torch.tensor(ck["std"]), list(ck["emd_index"]), list(ck["center_index"]))
    model.load_state_dict(ck["state_dict"])
    model.eval()
    return model, ck


def _plots(out: Path, history: dict, metrics: dict, classes: tuple[str, ...]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ep = np.arange(1, len(history["train_loss"]) + 1)
    ax[0].plot(ep, history["train_loss"], label="train")
    ax[0].plot(ep, history["val_loss"], label="validation")
    ax[0].set(xlabel="epoch", ylabel="cross-entropy", title="loss")
    ax[0].legend()
    ax[1].plot(ep, history["val_acc"])
    ax[1].set(xlabel="epoch", ylabel="accuracy", title="validation accuracy", ylim=(0, 1))
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=100)
    plt.close(fig)
    norm = np.array(metrics["confusion_normalised"])
    fig, ax = plt.subplots(figsize=(1.2 * len(classes) + 2, 1.0 * len(classes) + 1.5))
    ax.imshow(norm, vmin=0, vmax=1, cmap="Blues")
    for i in range(len(classes)):
        for j in range(len(classes)):
            ax.text(j, i, f"{norm[i, j]:.2f}", ha="center", va="center",
                    color="white" if norm[i, j] > 0.5 else "black")
    ax.set_xticks(range(len(classes)), classes, rotation=30, ha="right")
    ax.set_yticks(range(len(classes)), classes)
    ax.set(xlabel="estimated class", ylabel="label of input data",
           title=f"test accuracy {metrics['accuracy']:.3f}")
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


def _log(progress: bool, msg: str) -> None:
    if progress:
        print(msg, file=sys.stderr, flush=True)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tactile-train", description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path, help="dataset folder (takes: .csv + .json)")
    p.add_argument("--out", type=Path, required=True, help="run folder to write")
    p.add_argument("--config", type=Path, help="TOML file of settings (see TrainConfig)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting, e.g. --set hidden=32 --set emd_channels=accel_z")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
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
        current = getattr(TrainConfig, key)
        try:
            if isinstance(current, tuple):
                d[key] = [v for v in value.split(",") if v]
            elif isinstance(current, int):
                d[key] = int(value)
            elif isinstance(current, float):
                d[key] = float(value)
            else:
                d[key] = value
        except ValueError:
            raise ConfigError(f"--set {key}={value!r}: not a valid {type(current).__name__}") \
                from None
    return TrainConfig.from_dict(d)


def _main(args: argparse.Namespace) -> int:
    cfg = TrainConfig.from_toml(args.config) if args.config else TrainConfig()
    cfg = parse_sets(args.set, cfg)
    m = train(args.data, args.out, cfg, progress=not args.quiet)
    print(table(m, tuple(m["classes"]), f"test split ({m['split']})"))
    print(f"shifted windows: {m['shifted']}; trained in {m['train_seconds']} s; run in {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run("tactile-train", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
