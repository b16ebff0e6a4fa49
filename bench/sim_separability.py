"""Is texture learnable across simulated users? Test accuracy on users that training never saw.

For the pen paper's two experiments -- (1) desk, cardboard, non-woven cloth, paper; (2)
non-contact, paper, non-woven cloth, plastic folder, mouse pad -- this script simulates
``--users`` users x textures x ``--seconds`` s (user ``k`` of a texture is take ``k`` of
``tactile-sim --dataset``: its own session, drawn from the take's seed, as separately recorded
sessions would be), cuts 50-sample windows every 25 samples, puts the first 2/3 of the users in
training and the rest in test, and reports test accuracy and per-class recall of:

- ``pressure``: mean pressure of the window alone, nearest class centroid (the "too easy"
  guard: if this scores high, the push level gives the texture away);
- ``logistic``: multinomial logistic regression on per-window features (per channel: log RMS
  after removing the window mean, log band energies 0-5, 5-15 and 15-50 Hz; log mean pressure);
- ``lstm``: a 1-layer LSTM (32 hidden) on the 8 raw channels normalised with training-set
  mean/std, the label read after the window's last sample, as in the pen paper.

It prints figures; it asserts nothing. Single-threaded; about a minute on one core.

Usage: python bench/sim_separability.py [--users 24] [--seconds 30] [--epochs 10] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch

from tactile.device.sim import PenSimulator, take_seed

EXPERIMENTS = {
    "experiment 1": ("desk", "cardboard", "nonwoven_cloth", "paper"),
    "experiment 2": ("non_contact", "paper", "nonwoven_cloth", "plastic_folder", "mouse_pad"),
}
WINDOW, HOP, FS = 50, 25, 100.0
BANDS = ((0.0, 5.0), (5.0, 15.0), (15.0, 50.1))


def windows(raw: np.ndarray) -> np.ndarray:
    """(n_windows, WINDOW, 8) float32 windows of one take."""
    starts = range(0, len(raw) - WINDOW + 1, HOP)
    return np.stack([raw[s : s + WINDOW] for s in starts]).astype(np.float32)


def simulate_users(
    textures: tuple[str, ...], users: int, seconds: float, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Windows (N, 50, 8), labels (N,) and user index (N,) for every (texture, user) take."""
    xs, ys, us = [], [], []
    n = int(round(seconds * FS))
    for k in range(users):
        for label, texture in enumerate(textures):
            w = windows(PenSimulator(texture, seed=take_seed(seed, texture, k)).read(n))
            xs.append(w)
            ys.append(np.full(len(w), label))
            us.append(np.full(len(w), k))
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(us)


def features(x: np.ndarray) -> np.ndarray:
    """Per-window features (N, 29): 7 channels (pressure once) x (log RMS, 3 log band
    energies) and the log mean pressure."""
    x = x[:, :, 1:].astype(np.float64)  # pressure_0 == pressure_1: keep one
    centred = x - x.mean(axis=1, keepdims=True)
    rms = np.log(np.sqrt((centred**2).mean(axis=1)) + 1.0)  # (N, 7), +1 count floor
    spec = np.abs(np.fft.rfft(centred * np.hanning(WINDOW)[None, :, None], axis=1)) ** 2
    freqs = np.fft.rfftfreq(WINDOW, 1.0 / FS)
    bands = [np.log(spec[:, (freqs >= lo) & (freqs < hi)].sum(axis=1) + 1.0) for lo, hi in BANDS]
    level = np.log(x[:, :, 0].mean(axis=1) + 1.0)[:, None]
    return np.concatenate([rms, *bands, level], axis=1)


def recall(pred: np.ndarray, y: np.ndarray, n_classes: int) -> list[float]:
    return [float((pred[y == c] == c).mean()) for c in range(n_classes)]


def nearest_centroid(tr: np.ndarray, ytr: np.ndarray, te: np.ndarray, n: int) -> np.ndarray:
    centroids = np.array([tr[ytr == c].mean(axis=0) for c in range(n)])
    return ((te[:, None] - centroids[None]) ** 2).sum(axis=-1).argmin(axis=1)


def logistic(
    tr: np.ndarray, ytr: np.ndarray, te: np.ndarray, n: int, steps: int = 300
) -> np.ndarray:
    """Multinomial logistic regression (standardised features, small L2), full-batch L-BFGS."""
    mu, sd = tr.mean(axis=0), tr.std(axis=0) + 1e-9
    a = torch.tensor((tr - mu) / sd, dtype=torch.float32)
    b = torch.tensor((te - mu) / sd, dtype=torch.float32)
    y = torch.tensor(ytr)
    model = torch.nn.Linear(a.shape[1], n)
    opt = torch.optim.LBFGS(model.parameters(), max_iter=steps, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = torch.nn.functional.cross_entropy(model(a), y)
        loss = loss + 1e-3 * (model.weight**2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        return model(b).argmax(dim=1).numpy()


class _Lstm(torch.nn.Module):
    def __init__(self, n_in: int, n_out: int, hidden: int = 32) -> None:
        super().__init__()
        self.lstm = torch.nn.LSTM(n_in, hidden, batch_first=True)
        self.head = torch.nn.Linear(hidden, n_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out, _ = self.lstm(x)
        return self.head(out[:, -1])  # the label after the window's last sample


def lstm(
    tr: np.ndarray,
    ytr: np.ndarray,
    te: np.ndarray,
    n: int,
    epochs: int,
    seed: int,
    hidden: int = 32,
    lr: float = 6e-3,
) -> np.ndarray:
    torch.manual_seed(seed)
    mu, sd = tr.reshape(-1, 8).mean(axis=0), tr.reshape(-1, 8).std(axis=0) + 1e-6
    a = torch.tensor((tr - mu) / sd, dtype=torch.float32)
    b = torch.tensor((te - mu) / sd, dtype=torch.float32)
    y = torch.tensor(ytr)
    model = _Lstm(8, n, hidden)
    opt = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=1e-4)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(epochs):
        model.train()
        for idx in torch.randperm(len(a), generator=gen).split(64):
            opt.zero_grad()
            torch.nn.functional.cross_entropy(model(a[idx]), y[idx]).backward()
            opt.step()
    model.eval()
    with torch.no_grad():
        return torch.cat([model(c).argmax(dim=1) for c in b.split(1024)]).numpy()


def run(name: str, textures: tuple[str, ...], args: argparse.Namespace) -> None:
    t0 = time.perf_counter()
    x, y, user = simulate_users(textures, args.users, args.seconds, args.seed)
    t_sim = time.perf_counter() - t0
    n_train = (2 * args.users) // 3
    tr, te = user < n_train, user >= n_train
    n = len(textures)
    feats = features(x)
    preds = {
        "pressure": nearest_centroid(feats[tr][:, -1:], y[tr], feats[te][:, -1:], n),
        "logistic": logistic(feats[tr], y[tr], feats[te], n),
        "lstm": lstm(x[tr], y[tr], x[te], n, args.epochs, args.seed),
    }
    t_all = time.perf_counter() - t0
    print(
        f"\n{name}: {n_train} training users, {args.users - n_train} test users, "
        f"{tr.sum()} / {te.sum()} windows (simulation {t_sim:.0f} s, total {t_all:.0f} s)"
    )
    short = [t[:10] for t in textures]
    print("model       accuracy  " + "".join(s.rjust(11) for s in short))
    for model, pred in preds.items():
        acc = float((pred == y[te]).mean())
        rec = recall(pred, y[te], n)
        print(f"{model:10s}  {acc:8.3f}  " + "".join(f"{r:11.3f}" for r in rec))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--users", type=int, default=24, help="simulated users per texture")
    parser.add_argument("--seconds", type=float, default=30.0, help="seconds per take")
    parser.add_argument("--epochs", type=int, default=10, help="LSTM training epochs")
    parser.add_argument("--seed", type=int, default=0, help="base seed of the takes")
    parser.add_argument("--only", choices=("1", "2"), help="run one experiment only")
    args = parser.parse_args(argv)
    if args.users < 3:
        print("error: --users must be >= 3", file=sys.stderr)
        return 1
    torch.set_num_threads(1)
    print("test accuracy and per-class recall on unseen users (50-sample windows, hop 25)")
    for i, (name, textures) in enumerate(EXPERIMENTS.items(), start=1):
        if args.only in (None, str(i)):
            run(name, textures, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
