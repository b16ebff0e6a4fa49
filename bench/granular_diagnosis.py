"""Why the granular-media models trail a logistic regression on BioTac: the figures.

    tactile-import-biotac ../shared/datasets/biotac-bolt/*.h5 --out data/biotac
    python bench/granular_diagnosis.py data/biotac --cache feats.pt

On the training and validation windows only (the test split is never read past its cut):
the SF-RNN config's (``configs/granular/biotac-all-sf_rnn.toml``) data images and codes,
dictionaries learned from the training images as training learns them (seed 0), then per
modality and for all of them together the validation accuracy of a logistic regression
(standardised on the training windows, ``C`` in 0.01..10 picked on validation, the figure
printed is that validation accuracy) on per-window summaries:

* ``mean code`` against ``mean |code|`` (the codes pooled over the window's steps, signed,
  and as magnitudes): what a pooled signed code keeps of a window;
* ``mean image`` against ``rms image`` (the F-RNN's inputs, pooled the same two ways);
* ``energy kept``: per modality, the share of the validation images' energy that the codes
  reconstruct (``1 - sum |x - c D|^2 / sum |x|^2``) and the median over frames of the same
  ratio frame by frame;
* ``level``: each unit's mean over the window (the DC levels: a pressure image of IMFs
  has none, the paper drops EMD's residue);
* the band-energy baseline's features (``bench/baselines.py``'s ``window_features`` plus
  the vibration's bands at 2.2 kHz) on the same windows;
* the linear model's own features (``model = "linear"``: the log mean energy of each IMF over
  the window), which its trained classifier can be compared with.

``--log RUN.log`` (a ``tactile-train`` log of a run at the toolkit's budget, e.g. the config
above) adds what each early-stopping budget would have kept of that run's validation curve:
the cut one (``select = "loss"``, patience 5, at most 20 epochs) and the default one
(``select = "accuracy"``, patience 25, at most 150 epochs).

``--cache FILE`` keeps the images and codes (a few hundred MB) so that a rerun takes
seconds; the first run computes them (EMD and OMP of every window: 2-4 min of CPU).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch

from tactile.device.recordings import load_dataset
from tactile.training import feature_pass
from tactile.training.config import TrainConfig
from tactile.training.dist import Dist
from tactile.training.granular import learn_dictionaries
from tactile.training.log import Log
from tactile.training.models import build_model
from tactile.training.prepare import _features, check_inputs, prepare

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "granular" / "biotac-all-sf_rnn.toml"
CS = (0.01, 0.1, 1.0, 10.0)


def compute(data: Path, cfg: TrainConfig) -> dict:
    """Images and codes (N, S, F) of the training and validation windows, the dictionaries,
    the layout and the windows' raw values (N, T, C), labels and channel names."""
    dist, log = Dist(), Log(False, True)
    takes = load_dataset(data)
    classes, channels = check_inputs(data, takes, cfg)
    prep = prepare(takes, classes, channels, cfg, log, dist)
    parts = {k: prep.parts[k] for k in ("train", "val")}  # the test windows stay unread
    model = build_model(prep.cfg, len(classes), torch.from_numpy(prep.norm.mean),
                        torch.from_numpy(prep.norm.std), channels=channels,
                        rate_hz=takes[0].info.sample_rate_hz)
    pre = model.pre
    with feature_pass.feature_pass():
        images = {k: _features(pre.images, w, log, k, dist) for k, w in parts.items()}
        energy = {k: _features(lambda x: energy_of(pre, x), w, log, k, dist)
                  for k, w in parts.items()}
        learn_dictionaries(pre, images["train"], prep.cfg.seed, dist)
        codes = {k: torch.cat([pre.post(c) for c in v.split(32)]) for k, v in images.items()}
    return {"images": images, "codes": codes, "energy": energy,
            "dicts": [c.dictionary.detach().clone() for c in pre.coders],
            "layout": [(m.name, m.features, m.atoms, list(m.index)) for m in pre.layout],
            "x": {k: torch.from_numpy(w.x) for k, w in parts.items()},
            "y": {k: torch.from_numpy(np.asarray(w.y)) for k, w in parts.items()},
            "mean": torch.from_numpy(prep.norm.mean), "std": torch.from_numpy(prep.norm.std),
            "channels": list(channels), "rate": takes[0].info.sample_rate_hz}


def energy_of(pre, x: torch.Tensor) -> torch.Tensor:
    """(B, 1, F): the linear model's features of windows x (its ``energy`` mode)."""
    z = pre.normalise(x)
    return pre.energy(z, pre.decompose(z))


def val_accuracy(train: np.ndarray, val: np.ndarray, y: dict) -> float:
    """The logistic regression's validation accuracy, ``C`` picked on validation."""
    from sklearn.linear_model import LogisticRegression
    from threadpoolctl import threadpool_limits

    mu, sd = train.mean(0), train.std(0) + 1e-9
    a, b = (train - mu) / sd, (val - mu) / sd
    best = 0.0
    with threadpool_limits(1):
        for c in CS:
            m = LogisticRegression(C=c, max_iter=2000).fit(a, y["train"])
            best = max(best, float((m.predict(b) == y["val"]).mean()))
    return best


def blocks(d: dict, key: str) -> list[tuple[str, slice]]:
    """(modality, its slice of the features) for ``images`` or ``codes``."""
    out, at = [], 0
    for name, n_feat, n_atoms, _ in d["layout"]:
        n = n_feat if key == "images" else n_atoms
        out.append((name, slice(at, at + n)))
        at += n
    return out + [("all", slice(0, at))]


def energy_kept(d: dict) -> list[tuple[str, float, float]]:
    """Per modality: the share of the validation images' energy the codes reconstruct,
    overall and the median frame's."""
    out = []
    img, codes = d["images"]["val"].double(), d["codes"]["val"].double()
    for (name, si), (_, sc), dic in zip(blocks(d, "images"), blocks(d, "codes"), d["dicts"]):
        x = img[:, :, si].reshape(-1, si.stop - si.start)
        rec = codes[:, :, sc].reshape(-1, sc.stop - sc.start) @ dic.double()
        err, tot = (x - rec).pow(2).sum(1), x.pow(2).sum(1)
        keep = tot > 0
        out.append((name, float(1 - err.sum() / tot.sum()),
                    float((1 - err[keep] / tot[keep]).median())))
    return out


BUDGETS = (("cut: select loss, patience 5, 20 epochs", "loss", 5, 20),
           ("default: select accuracy, patience 25, 150 epochs", "accuracy", 25, 150))


def budgets(log: Path) -> list[str]:
    """Per early-stopping budget, the epoch it keeps of the logged run's fit and that
    epoch's validation accuracy (the run must have gone on at least as long)."""
    from tactile.training.loop import improves

    pat = re.compile(r"^fit epoch (\d+)/\d+: .*val loss ([\d.]+), val acc ([\d.]+)")
    curve = [(float(m[2]), float(m[3])) for m in map(pat.match, log.read_text().splitlines())
             if m]
    out = []
    for label, rule, patience, epochs in BUDGETS:
        best, best_loss, best_acc, stale = 0, float("inf"), -1.0, 0
        for e, (loss, acc) in enumerate(curve[:epochs]):
            if improves(rule, acc, loss, best_loss, best_acc):
                best, best_loss, best_acc, stale = e, loss, acc, 0
            else:
                stale += 1
                if stale >= patience:
                    break
        out.append(f"{label}: epoch {best + 1}, validation accuracy {curve[best][1]:.3f}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path, help="tactile-import-biotac's folder")
    ap.add_argument("--log", type=Path, help="a tactile-train log at the default budget")
    ap.add_argument("--cache", type=Path, help="keep the images and codes here")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = TrainConfig.from_toml(CONFIG).replace(threads=1)
    d = torch.load(args.cache, weights_only=False) if args.cache and args.cache.exists() else {}
    if "energy" not in d:  # no cache, or one from before the linear model's features
        t0 = time.process_time()
        d = compute(args.data, cfg)
        print(f"features: {time.process_time() - t0:.0f} s CPU", file=sys.stderr)
        if args.cache:
            torch.save(d, args.cache)
    y = {k: v.numpy() for k, v in d["y"].items()}
    print(f"windows: train {len(y['train'])}, val {len(y['val'])}; {len(set(y['train']))} "
          "classes; logistic regression, validation accuracy:")
    print("| features | " + " | ".join(n for n, _ in blocks(d, "codes")) + " |")
    print("|---" * (1 + len(blocks(d, "codes"))) + "|")
    for label, key, fn in (
            ("mean code", "codes", lambda f: f.mean(1)),
            ("mean abs code", "codes", lambda f: f.abs().mean(1)),
            ("mean image", "images", lambda f: f.mean(1)),
            ("rms image", "images", lambda f: f.pow(2).mean(1).sqrt()),
            ("log rms image", "images", lambda f: 0.5 * torch.log(f.pow(2).mean(1) + 1e-12))):
        accs = [val_accuracy(fn(d[key]["train"][:, :, s]).double().numpy(),
                             fn(d[key]["val"][:, :, s]).double().numpy(), y)
                for _, s in blocks(d, key)]
        print(f"| {label} | " + " | ".join(f"{a:.3f}" for a in accs) + " |")
    # the DC levels of each modality's units (normalised), which a pressure image of IMFs lacks
    z = {k: ((x - d["mean"]) / d["std"]).mean(1).double().numpy() for k, x in d["x"].items()}
    levels = []
    for name, _, _, index in d["layout"]:
        levels.append(f"{name} {val_accuracy(z['train'][:, index], z['val'][:, index], y):.3f}")
    print("level (each unit's window mean): " + ", ".join(levels))
    sys.path.insert(0, str(ROOT / "bench"))
    from baselines import signal_features, window_features

    ch = d["channels"]
    pac = [ch.index(c) for c in ch if c.startswith("f0_pac_")]
    feats = {k: np.concatenate([window_features(x.numpy(), d["rate"]),
                                signal_features(x.numpy(), [pac], d["rate"])], axis=1)
             for k, x in d["x"].items()}
    print(f"band-energy baseline (+ vibration bands at 2.2 kHz): "
          f"{val_accuracy(feats['train'], feats['val'], y):.3f}")
    bands = {k: signal_features(x.numpy(), [pac], d["rate"]) for k, x in d["x"].items()}
    print(f"the vibration's bands at 2.2 kHz alone: "
          f"{val_accuracy(bands['train'], bands['val'], y):.3f}")
    e = {k: v[:, 0].double().numpy() for k, v in d["energy"].items()}
    print(f"the linear model's features (log mean energy of each IMF, a unit's mean and log std "
          f"without IMFs; {e['train'].shape[1]}): {val_accuracy(e['train'], e['val'], y):.3f}")
    print("energy kept by the codes (validation images): " + ", ".join(
        f"{n} {a:.3f} (median frame {m:.3f})" for n, a, m in energy_kept(d)))
    c = d["codes"]["train"].double()
    print("|mean code| / mean |code| over the training windows, summed over atoms: " + ", ".join(
        f"{n} {(c[:, :, s].mean(1).abs().sum() / c[:, :, s].abs().mean(1).sum()).item():.3f}"
        for n, s in blocks(d, "codes")))
    if args.log:
        print(f"early stopping on {args.log.name}'s validation curve: " + "; ".join(
            budgets(args.log)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
