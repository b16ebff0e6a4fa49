"""Evaluate a trained run on a dataset: window and per-take accuracy, confusion, robustness.

:func:`evaluate_run` (the figures ``tactile-eval RUN/ DATA`` prints) measures the accuracy over
windows, the majority vote per take (the label most of a take's windows got, against the
take's label: what trial-based datasets report), per-class recall and the row-normalised
confusion table laid out as the pen paper's Tables 1 and 2 ("label of input data" rows,
"estimated class" columns), then the granular-media paper's robustness check: the same windows
shifted in time by up to +/-0.2 s. If DATA holds the run's test takes, only their test rows are
evaluated; otherwise all of DATA. Torch uses the run's ``threads`` setting.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from tactile.errors import ConfigError
from tactile.training import feature_pass
from tactile.training.checkpoint import load_checkpoint
from tactile.training.config import apply_threads, resolve_threads
from tactile.training.data import Windows, cut, model_data, ordered_signals
from tactile.training.label_stream import stream_figures
from tactile.training.model import TextureModel


def per_take_line(m: dict) -> str:
    """The per-take majority vote of ``m`` (a run's or an evaluation's figures), one line."""
    n = m["takes"]
    return f"per take (majority vote): {m['take_accuracy']:.3f} over {n} take{'s' * (n != 1)}"


SHIFTS_S = (-0.2, -0.1, 0.1, 0.2)  # the "novel" set: windows moved by up to +/-0.2 s


@torch.no_grad()
def predict(
    model: TextureModel, w: Windows, batch: int = 512, feats: torch.Tensor | None = None
) -> np.ndarray:
    """(N, classes) probabilities, following the model's state mode.

    ``window``: every window from a zero state. ``carry``: the state is carried from each window
    to the next one of the same gap-free run (ordered by start), reset at every run's start,
    exactly as the runtime does on a stream. ``feats``: the windows' features
    (``model.pre``), when already computed (training validates every epoch without redoing EMD).
    """
    model.eval()
    if feats is None:
        feats = _features(model, torch.from_numpy(w.x), batch)
    dev = next(model.head.parameters()).device  # the head may sit on a GPU while training

    def zero(n: int) -> tuple[torch.Tensor, torch.Tensor]:
        return tuple(t.to(dev) for t in model.zero_state(n))

    out = np.zeros((len(w), model.n_classes), np.float32)
    if model.cfg.state == "window":
        for i in range(0, len(w), batch):
            f = feats[i : i + batch].to(dev)
            logits = model.head(f, *zero(len(f)))[0]
            out[i : i + batch] = torch.softmax(logits, dim=1).cpu().numpy()
        return out
    for rows in runs(w):  # carry: one run at a time, window after window
        h, c = zero(1)
        for r in rows:
            logits, h, c = model.head(feats[r : r + 1].to(dev), h, c)
            out[r] = torch.softmax(logits, 1)[0].cpu().numpy()
    return out


def _features(model: TextureModel, x: torch.Tensor, batch: int = 512) -> torch.Tensor:
    """The features as training computes them (its feature pass: EMD and codes in float64)."""
    with feature_pass.feature_pass():
        return torch.cat([model.pre(x[i : i + batch]) for i in range(0, len(x), batch)])


def runs(w: Windows) -> list[np.ndarray]:
    """Row indices of each gap-free run, ordered by window start."""
    order = np.lexsort((w.start, w.run))
    bounds = np.flatnonzero(np.diff(w.run[order])) + 1
    return np.split(order, bounds)


def confusion(y: np.ndarray, pred: np.ndarray, n: int) -> np.ndarray:
    """(n, n) counts: rows the true label, columns the estimate."""
    m = np.zeros((n, n), np.int64)
    np.add.at(m, (y, pred), 1)
    return m


def summary(y: np.ndarray, probs: np.ndarray, classes: tuple[str, ...]) -> dict:
    pred = probs.argmax(1)
    m = confusion(y, pred, len(classes))
    rows = m.sum(1, keepdims=True)
    norm = np.divide(m, rows, out=np.zeros(m.shape), where=rows > 0)
    return {
        "windows": int(len(y)),
        "accuracy": float((pred == y).mean()) if len(y) else float("nan"),
        # (None: the class has no window here, nothing to recall)
        "recall": {c: float(norm[i, i]) if rows[i, 0] else None for i, c in enumerate(classes)},
        "confusion": m.tolist(),
        "confusion_normalised": norm.round(4).tolist(),
    }


def per_take(w: Windows, probs: np.ndarray, names: list[str]) -> dict:
    """The majority vote of each take's windows (ties: the larger summed probability) against
    the take's label. ``names``: every take's name, indexed by ``w.take``. Returns ``takes``
    (count), ``take_accuracy`` (share of takes whose vote is their label) and ``per_take``
    ({name: {label, vote, windows, share}}, share: of its windows that voted for ``vote``)."""
    pred = probs.argmax(1)
    n_classes = probs.shape[1]
    out = {}
    for t in np.unique(w.take):
        sel = w.take == t
        votes = np.bincount(pred[sel], minlength=n_classes).astype(np.float64)
        votes += probs[sel].sum(0) / (sel.sum() + 1.0)  # < 1: breaks ties only
        vote = int(votes.argmax())
        out[names[int(t)]] = {"label": int(w.y[sel][0]), "vote": vote, "windows": int(sel.sum()),
                              "share": float((pred[sel] == vote).mean())}
    right = [v["vote"] == v["label"] for v in out.values()]
    return {"takes": len(out), "take_accuracy": float(np.mean(right)) if right else float("nan"),
            "per_take": out}


def shifted_line(s: dict | None) -> str:
    """The robustness check as one line: ``shifted windows (robustness): -0.2s 0.812, ...``,
    or ``not measured`` and why (:func:`shifted`'s ``not_measured``)."""
    if not s or "not_measured" in s:
        why = f": {s['not_measured']}" if s else ""
        return f"shifted windows (robustness): not measured{why}"
    return "shifted windows (robustness): " + ", ".join(f"{k} {v:.3f}" for k, v in s.items())


def table(s: dict, classes: tuple[str, ...], title: str = "") -> str:
    """The confusion table as the pen paper prints it (row-normalised, 3 decimals)."""
    norm = np.array(s["confusion_normalised"])
    width = max(9, *(len(c) + 1 for c in classes))
    head = "label of input data".ljust(22) + "estimated class".ljust(width * len(classes))
    lines = [title] if title else []
    lines += [head.rstrip(), " " * 22 + "".join(c.rjust(width) for c in classes)]
    counts = np.array(s["confusion"]).sum(1)
    for i, c in enumerate(classes):  # a class with no window here: "-", not a row of zeros
        lines.append(c.ljust(22) + "".join((f"{v:.3f}" if counts[i] else "-").rjust(width)
                                           for v in norm[i]))
    lines.append(f"accuracy {s['accuracy']:.3f} over {s['windows']} windows")
    return "\n".join(lines)


def shifted(model: TextureModel, takes, classes, channels, rows, window: int, hop: int,
            rate: float) -> dict:
    """Accuracy on windows moved by each of :data:`SHIFTS_S` (the "novel" set). A shift that
    the hop divides is left out: its windows are the test windows again (one hop on), so its
    figure would be the test accuracy, not a robustness figure (at the defaults' hop of 10
    samples at 100 Hz, every shift); so is a shift that leaves no window inside its segment
    (each test segment holds one window, at its start or end). With none measured the result
    is ``{"not_measured": why}`` (empty: no window fits at any shift)."""
    out = {}
    off_grid = [s for s in SHIFTS_S if round(s * rate) % hop]
    for s in off_grid:
        try:
            w = cut(takes, classes, channels, window, hop, rows, shift=round(s * rate))
        except ConfigError:  # no window fits at this shift: nothing to measure there
            continue
        out[f"{s:+.1f}s"] = summary(w.y, predict(model, w), classes)["accuracy"]
    if out:
        out["mean"] = float(np.mean(list(out.values())))
    elif not off_grid:
        out["not_measured"] = (f"the hop ({hop} samples, {hop / rate:g} s) divides every "
                               "shift, so the shifted windows are the test windows again")
    return out


def evaluate_run(run_dir: Path, data: Path, threads: int | None = None,
                 smoothing=None) -> dict:
    """The figures of ``run_dir``'s model on ``data`` (see the module's text). ``threads``:
    torch threads (default: the run's ``threads`` setting, resolved on this machine).
    ``label_stream``: the evaluated rows as label streams, raw and post-processed with
    ``smoothing`` (a :class:`~tactile.postprocess.smoothing.SmoothingSettings`; None: the
    setting calibrated on the run's validation takes), by
    :func:`tactile.training.label_stream.stream_figures`."""
    model, ck = load_checkpoint(run_dir)
    cfg = model.cfg
    s_threads = apply_threads(threads or resolve_threads(cfg.threads))
    takes, rows, scope, trained = model_data(ck, data, str(data), ordered_signals(cfg))
    classes, channels = tuple(ck["classes"]), tuple(ck["channels"])
    rate = float(ck["sample_rate_hz"])
    w = cut(takes, classes, channels, cfg.window, cfg.hop, rows)
    probs = predict(model, w)
    s = summary(w.y, probs, classes)
    s.update(per_take(w, probs, [t.path.stem for t in takes]))
    s["scope"] = scope
    s["seen_takes"] = trained
    s["threads"] = s_threads
    s["shifted"] = shifted(model, takes, classes, channels, rows, cfg.window, cfg.hop, rate)
    s["classes"] = list(classes)
    s["label_stream"] = stream_figures(model, ck, takes, data.name, rows,
                                       lambda v: predict(model, v), smoothing)
    return s


__all__ = ["predict", "summary", "per_take", "per_take_line", "shifted", "shifted_line",
           "table", "evaluate_run", "runs", "confusion", "SHIFTS_S"]
