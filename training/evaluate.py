"""Evaluation: predictions over windows, the pen paper's confusion tables, and ``tactile-eval``.

    tactile-eval RUN/ DATA [--json]

prints accuracy, per-class recall and the row-normalised confusion table laid out as the pen
paper's Tables 1 and 2 ("label of input data" rows, "estimated class" columns), then the
granular-media paper's robustness check: the same windows shifted in time by up to +/-0.2 s.
If DATA holds the run's test takes, only their test rows are evaluated; otherwise all of DATA.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from tactile.cli import Parser, add_debug, run
from tactile.device.recording import load_dataset
from tactile.errors import ConfigError, RecordingError
from tactile.training.data import Windows, cut
from tactile.training.model import TextureModel

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
    out = np.zeros((len(w), model.head.out.out_features), np.float32)
    if model.cfg.state == "window":
        for i in range(0, len(w), batch):
            h, c = model.zero_state(len(feats[i : i + batch]))
            logits = model.head(feats[i : i + batch], h, c)[0]
            out[i : i + batch] = torch.softmax(logits, dim=1).numpy()
        return out
    for rows in _runs(w):  # carry: one run at a time, window after window
        h, c = model.zero_state(1)
        for r in rows:
            logits, h, c = model.head(feats[r : r + 1], h, c)
            out[r] = torch.softmax(logits, 1)[0].numpy()
    return out


def _features(model: TextureModel, x: torch.Tensor, batch: int = 512) -> torch.Tensor:
    return torch.cat([model.pre(x[i : i + batch]) for i in range(0, len(x), batch)])


def _runs(w: Windows) -> list[np.ndarray]:
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
        "recall": {c: float(norm[i, i]) for i, c in enumerate(classes)},
        "confusion": m.tolist(),
        "confusion_normalised": norm.round(4).tolist(),
    }


def table(s: dict, classes: tuple[str, ...], title: str = "") -> str:
    """The confusion table as the pen paper prints it (row-normalised, 3 decimals)."""
    norm = np.array(s["confusion_normalised"])
    width = max(9, *(len(c) + 1 for c in classes))
    head = "label of input data".ljust(22) + "estimated class".ljust(width * len(classes))
    lines = [title] if title else []
    lines += [head.rstrip(), " " * 22 + "".join(c.rjust(width) for c in classes)]
    for i, c in enumerate(classes):
        lines.append(c.ljust(22) + "".join(f"{v:.3f}".rjust(width) for v in norm[i]))
    lines.append(f"accuracy {s['accuracy']:.3f} over {s['windows']} windows")
    return "\n".join(lines)


def shifted(model: TextureModel, takes, classes, channels, rows, window: int, hop: int,
            rate: float) -> dict:
    """Accuracy on windows moved by each of :data:`SHIFTS_S` (the "novel" set)."""
    out = {}
    for s in SHIFTS_S:
        w = cut(takes, classes, channels, window, hop, rows, shift=round(s * rate))
        out[f"{s:+.1f}s"] = summary(w.y, predict(model, w), classes)["accuracy"]
    out["mean"] = float(np.mean(list(out.values())))
    return out


def evaluate_run(run_dir: Path, data: Path) -> dict:
    from tactile.training.train import load_checkpoint

    model, ck = load_checkpoint(run_dir)
    cfg = model.cfg
    takes = load_dataset(data)
    classes = tuple(ck["classes"])
    unknown = sorted({t.label for t in takes} - set(classes))
    if unknown:
        raise RecordingError(f"{data}: labels {unknown} are not among the model's {list(classes)}")
    names = [t.path.name for t in takes]
    test = {n: tuple(r) for n, r in ck["test_rows"].items()}
    if test and all(n in names for n in test):
        rows = {names.index(n): r for n, r in test.items()}
        scope = "the run's test split"
    else:
        rows = None
        scope = "every take in DATA"
    channels = tuple(ck["channels"])
    rate = float(ck["sample_rate_hz"])
    w = cut(takes, classes, channels, cfg.window, cfg.hop, rows)
    s = summary(w.y, predict(model, w), classes)
    s["scope"] = scope
    s["shifted"] = shifted(model, takes, classes, channels, rows, cfg.window, cfg.hop, rate)
    s["classes"] = list(classes)
    return s


def _main(args: argparse.Namespace) -> int:
    s = evaluate_run(args.run, args.data)
    if args.json:
        print(json.dumps(s))
        return 0
    classes = tuple(s["classes"])
    print(f"evaluated on {s['scope']}")
    print(table(s, classes))
    print("recall: " + ", ".join(f"{c} {v:.3f}" for c, v in s["recall"].items()))
    print("shifted windows (robustness): " + ", ".join(
        f"{k} {v:.3f}" for k, v in s["shifted"].items()))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = Parser(prog="tactile-eval", description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="run folder written by tactile-train")
    p.add_argument("data", type=Path, help="dataset folder")
    p.add_argument("--json", action="store_true", help="the figures as one JSON object")
    add_debug(p)
    return run("tactile-eval", _main, p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["predict", "summary", "table", "evaluate_run", "main", "ConfigError"]
