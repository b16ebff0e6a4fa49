"""A finished (or interrupted) run's folder: the checkpoint, the figures and the pictures.

    checkpoint.pt     weights + resolved config + classes, channels, rate, normalisation,
                      test rows and metrics (:func:`tactile.training.checkpoint.save_checkpoint`)
    metrics.json      the figures (:func:`run_metrics`); confusion.txt the paper-style table;
    curves.png, confusion.png
"""

from __future__ import annotations

import contextlib
import copy
import json
import platform
from importlib import metadata
from pathlib import Path

import numpy as np
import torch

import tactile
from tactile.errors import ConfigError, OutputError
from tactile.files import figure_bytes, write_whole
from tactile.training.checkpoint import CHECKPOINT, plain, save_checkpoint
from tactile.training.config import TrainConfig
from tactile.training.evaluate import per_take, predict, shifted, summary, table
from tactile.training.model import Classifier
from tactile.training.prepare import Prepared

# what a run's figures depend on beside the code and the data: PyTorch (training), numpy (the
# BLAS under its products), scikit-learn and the SciPy under it (the granular models'
# dictionaries, the blended regression), onnx and onnxruntime (the exported file and its check)
LIBRARIES = ("torch", "numpy", "scipy", "scikit-learn", "onnx", "onnxruntime")


def libraries() -> dict[str, str]:
    """The versions of Python, tactile and the :data:`LIBRARIES` installed here (those not
    installed are left out): the same code, data and seed give other figures under another
    scikit-learn's dictionary learning, so a run says what it ran on."""
    found = {"python": platform.python_version(), "tactile": tactile.__version__}
    for name in LIBRARIES:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return found


def libraries_line() -> str:
    """The benches' line of the :func:`libraries` this process runs on (a reused run's own are
    in its metrics.json)."""
    here = ", ".join(f"{k} {v}" for k, v in libraries().items())
    return f"<!-- libraries here: {here} (a reused run's own are in its metrics.json) -->"


def test_metrics(model: Classifier, prep: Prepared, feats: torch.Tensor) -> dict:
    """Window and per-take figures on the test split (``feats``: its windows' features)."""
    probs = predict(model, prep.parts["test"], feats=feats)
    metrics = summary(prep.parts["test"].y, probs, prep.classes)
    metrics.update(per_take(prep.parts["test"], probs, [t.path.stem for t in prep.takes]))
    return metrics


def run_metrics(model: Classifier, prep: Prepared, feats: torch.Tensor, history: dict,
                extra: dict, *, robustness: bool) -> dict:
    """The run's figures, in the order metrics.json lists them: the test split's
    (:func:`test_metrics`), with ``robustness`` the shifted windows' accuracy (``shifted``),
    then what every run says (classes, channels, the split, its window counts, the best epoch
    and its validation accuracy, the :func:`libraries` it ran on), then ``extra``: what only a
    finished, or only an interrupted, run says."""
    cfg, history_acc = prep.cfg, history["val_acc"]
    metrics = test_metrics(model, prep, feats)
    if robustness:
        metrics["shifted"] = shifted(model, prep.takes, prep.classes, cfg.channels,
                                     prep.split.test, cfg.window, cfg.hop,
                                     prep.takes[0].info.sample_rate_hz)
    metrics.update(
        classes=list(prep.classes), channels=list(cfg.channels), split=prep.split.description,
        split_windows={k: len(w) for k, w in prep.parts.items()},
        split_takes={part: {prep.takes[i].path.name: [int(a), int(b)] for i, (a, b) in
                            sorted(getattr(prep.split, part).items())}
                     for part in ("train", "val", "test")},
        best_epoch=history["best_epoch"],
        val_accuracy=history_acc[history["best_epoch"]] if history_acc else None,
        libraries=libraries(),
    )
    if history.get("blend"):  # what was validated is the mix: its figure, and the choice
        metrics.update(val_accuracy=history["blend"]["val_acc"], blend=history["blend"])
    metrics.update(extra)
    return metrics


def held_out_streams(model: Classifier, best: dict, prep: Prepared) -> list:
    """The label streams of the run's validation takes (as ``tactile-eval`` and ``tactile-export
    --data`` make them: :mod:`tactile.training.label_stream`) labelled by the first training's
    model (``best``: its head's weights at its best epoch), for a run that refit: its final
    model has trained on those takes, so its own labels of them would calibrate the label
    stream on data it has seen. ``model`` keeps its weights."""
    from tactile.training.label_stream import pieces, run_streams

    cfg = prep.cfg
    if not prep.split.val:
        return []
    rate = float(prep.takes[0].info.sample_rate_hz)
    groups = pieces(prep.takes, prep.split.val, prep.classes, cfg.channels, rate)
    final = copy.deepcopy(model.head.state_dict())
    model.head.load_state_dict(best)
    try:
        return run_streams(groups, prep.classes, rate, cfg.window, cfg.hop,
                           lambda w: predict(model, w))
    finally:
        model.head.load_state_dict(final)


def write_run(out: Path, cfg: TrainConfig, model: Classifier, metrics: dict, history: dict,
              prep: Prepared, held_out: list | None = None) -> None:
    """Write RUN/ (``out``): metrics.json, confusion.txt, the two pictures (:func:`plots`) and
    last the checkpoint of ``model`` and ``cfg``, each whole or not at all
    (:func:`~tactile.files.write_whole`), so that a checkpoint there means a whole run. A file
    that cannot be written is one error naming it (:class:`OutputError`, exit 4, for a full
    disk), and these files are removed (also an older run's, which ``--force`` overwrites: no
    folder mixes two runs; a resume.pt, written before them, stays). ``held_out``: see
    :func:`held_out_streams`."""
    out.mkdir(parents=True, exist_ok=True)
    files = {"metrics.json": (json.dumps(plain(metrics), indent=1) + "\n").encode(),
             "confusion.txt": (table(metrics, prep.classes, "test split") + "\n").encode(),
             **plots(history, metrics, prep.classes)}
    try:
        for name, data in files.items():
            write_whole(out / name, data)
        save_checkpoint(out / CHECKPOINT, cfg, model, metrics, classes=prep.classes,
                        takes=prep.takes, test=prep.split.test, norm=prep.norm,
                        held_out=held_out, seen=(*prep.split.train, *prep.split.val))
    except (OutputError, ConfigError) as e:
        for name in (*files, CHECKPOINT):
            with contextlib.suppress(OSError):
                (out / name).unlink(missing_ok=True)
        raise type(e)(f"{e}; the run is not saved") from None


def plots(history: dict, metrics: dict, classes: tuple[str, ...]) -> dict[str, bytes]:
    """A run's two pictures as PNG bytes: curves.png (the loss and validation accuracy per
    epoch, the kept epoch marked; with the blended regression, the blended model's validation
    accuracy at that epoch) and confusion.png (the row-normalised confusion with its
    counts)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ep = np.arange(1, len(history["train_loss"]) + 1)
    best = history["best_epoch"] + 1
    ax[0].plot(ep, history["train_loss"], label="train")
    ax[0].plot(ep[: len(history["val_loss"])], history["val_loss"], label="validation")
    ax[0].set(xlabel="epoch", ylabel="cross-entropy", title="loss")
    blend = history.get("blend")
    blended = bool(blend and blend["mix"] > 0)
    ax[1].plot(ep[: len(history["val_acc"])], history["val_acc"],
               label="the recurrent model alone" if blended else None)
    ax[1].set(xlabel="epoch", ylabel="accuracy", title="validation accuracy", ylim=(0, 1))
    for a in ax:  # the epoch whose weights were kept
        a.axvline(best, color="tab:red", linestyle="--", linewidth=1, label=f"best epoch {best}")
    if blended:  # the model as kept: that epoch's recurrent model with the regression
        ax[1].plot([best], [blend["val_acc"]], marker="*", markersize=11, linestyle="none",
                   color="tab:green", label=f"with the regression (mix {blend['mix']:g})")
        ax[1].legend(loc="lower right")
    ax[0].legend()
    fig.tight_layout()
    pictures = {"curves.png": figure_bytes(fig, "png", 100)}
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
    pictures["confusion.png"] = figure_bytes(fig, "png", 100)
    plt.close(fig)
    return pictures


__all__ = ["libraries", "libraries_line", "test_metrics", "run_metrics", "held_out_streams",
           "write_run", "plots"]
