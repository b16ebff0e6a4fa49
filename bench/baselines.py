"""The default model against a band-energy logistic regression, on the same windows, per dataset
and seed; prints one markdown table (mean and spread over the seeds) for docs/results.md.

    python bench/baselines.py --out runs/baselines                  # 4 datasets x seeds 0, 1, 2
    python bench/baselines.py --out runs/baselines --only small --seeds 0

Datasets (``--only``, repeatable):

* ``small``: ``tactile-sim --dataset D --takes 6`` (7 textures x 6 simulated users x 60 s), the
  default split by user (3 users train, 1 validates, 2 test).
* ``readme``: the README's set (24 users x 5 textures x 60 s) with the README's ``hop=25``.
* ``hapmat``: the HapMat stick IMU (``tactile-import-hapmat``), ``split=time``.
* ``biotac``: the BioTac BOLT recordings (5 objects, 74 trials, two fingers) as a user gets them:
  ``tactile-import-biotac ../shared/datasets/biotac-bolt/*.h5 --out CACHE`` (done once, into
  ``--cache``, outside the repository), then trained on that folder: the importer's 88 plain
  channels at 100 Hz, one take per trial, split by trial: the fifth repetition of every object
  and pressure tests (``test = "repetition:5"``), one of the other four validates (drawn from
  the seed); ``hop=50`` (windows do not overlap) to keep 88-channel windows in memory. Needs the
  ``[biotac]`` extra (h5py); skipped, saying why, without it or the files.

The baseline: per window and channel the mean, the log standard deviation and the log energy of
the mean-free, Hann-tapered window in :data:`N_BANDS` equal bands from 0 Hz to the Nyquist
frequency; standardised on the training windows; scikit-learn's multinomial
``LogisticRegression``, its ``C`` picked from :data:`CS` on the validation windows (and, when the
defaults refit on training + validation windows, refitted on them too). The defaults train with
``tactile.training.train.train`` and one thread; each run's wall time and its CPU time (user +
sys of this process) are printed.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from tactile.device.hapmat import import_hapmat
from tactile.device.recording import Take, load_dataset
from tactile.device.sim_cli import make_dataset
from tactile.device.simulator import TEXTURES
from tactile.training import train as train_module
from tactile.training.config import TrainConfig
from tactile.training.data import channel_index, classes_of, split_windows

SHARED = Path(__file__).resolve().parents[2] / "shared" / "datasets"
HAPMAT = SHARED / "hapmat" / "hapmat_stick_imu.npz"
BIOTAC = SHARED / "biotac-bolt"
README_TEXTURES = ("non_contact", "paper", "nonwoven_cloth", "plastic_folder", "mouse_pad")
DATASETS = ("small", "readme", "hapmat", "biotac")
N_BANDS = 5
CS = (0.01, 0.1, 1.0, 10.0)
# the data settings of each dataset (everything else: the defaults)
SETTINGS = {"small": {}, "readme": {"hop": 25}, "hapmat": {"split": "time"},
            "biotac": {"hop": 50, "test": "repetition:5"}}
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "tactile-bench"


def window_features(x: np.ndarray, rate: float, n_bands: int = N_BANDS) -> np.ndarray:
    """(N, T, C) windows -> (N, C * (2 + n_bands)): per channel the mean, log std and log energy
    of the mean-free, Hann-tapered window in ``n_bands`` equal bands up to ``rate / 2``."""
    z = x.astype(np.float64)
    mean = z.mean(axis=1)
    z = z - mean[:, None]
    log_std = np.log(z.std(axis=1) + 1e-9)
    power = np.abs(np.fft.rfft(z * np.hanning(z.shape[1])[None, :, None], axis=1)) ** 2
    freqs = np.fft.rfftfreq(z.shape[1], 1.0 / rate)
    edges = np.linspace(0.0, rate / 2, n_bands + 1)
    edges[-1] = np.inf
    bands = [np.log(power[:, (freqs >= lo) & (freqs < hi)].sum(axis=1) + 1e-12)
             for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    return np.concatenate([mean, log_std, *bands], axis=1)


def band_logistic(takes: list[Take], cfg: TrainConfig) -> dict:
    """The baseline on the windows ``cfg`` gives the default model: accuracies and timings."""
    from sklearn.linear_model import LogisticRegression
    from threadpoolctl import threadpool_limits

    t0, c0 = time.perf_counter(), _cpu()
    classes = classes_of(takes)
    channels = tuple(takes[0].channels[i] for i in channel_index(takes[0], cfg.channels))
    rate = takes[0].info.sample_rate_hz
    _, parts = split_windows(takes, classes, channels, cfg)
    feats = {k: window_features(w.x, rate) for k, w in parts.items()}
    mu, sd = feats["train"].mean(axis=0), feats["train"].std(axis=0) + 1e-9
    x = {k: (f - mu) / sd for k, f in feats.items()}
    y = {k: w.y for k, w in parts.items()}

    def fit(c: float, xs: np.ndarray, ys: np.ndarray) -> LogisticRegression:
        # one BLAS thread, as the defaults get one torch thread: two threads on a busy 2-core
        # machine spin (the BioTac fits took 5 min CPU with two, 20 s with one)
        with threadpool_limits(1):
            return LogisticRegression(C=c, max_iter=2000).fit(xs, ys)

    val_acc = {c: float((fit(c, x["train"], y["train"]).predict(x["val"]) == y["val"]).mean())
               for c in CS}
    best_c = max(CS, key=lambda c: (val_acc[c], -c))  # ties: the stronger regularisation
    if cfg.refits:
        model = fit(best_c, np.concatenate([x["train"], x["val"]]),
                    np.concatenate([y["train"], y["val"]]))
    else:
        model = fit(best_c, x["train"], y["train"])
    return {"accuracy": float((model.predict(x["test"]) == y["test"]).mean()),
            "val_accuracy": val_acc[best_c], "C": best_c,
            "split_windows": {k: len(w) for k, w in parts.items()},
            "wall_seconds": time.perf_counter() - t0, "cpu_seconds": _cpu() - c0}


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def import_biotac_cached(cache: Path) -> Path:
    """The BioTac dataset folder, imported once with ``tactile-import-biotac`` into ``cache``
    (into a sibling folder first, renamed when the import succeeded: a folder that is there is
    whole)."""
    data = cache / "biotac"
    if data.exists():
        return data
    part = cache / "biotac.partial"
    if part.exists():
        for f in part.iterdir():
            f.unlink()
    cache.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "tactile.device.biotac", *map(str, sorted(BIOTAC.glob("*.h5"))),
           "--out", str(part)]
    print(f"<!-- importing: tactile-import-biotac {BIOTAC}/*.h5 --out {part} -->", flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    part.rename(data)
    return data


def prepare(name: str, out: Path, cache: Path = CACHE) -> tuple[Path, list[Take]] | str:
    """(data folder, takes) of a dataset, or why it is skipped."""
    data = out / f"data-{name}"
    if name == "small" and not data.exists():
        make_dataset(data, 6, TEXTURES, 60.0, seed=0)
    elif name == "readme" and not data.exists():
        make_dataset(data, 24, README_TEXTURES, 60.0, seed=0)
    elif name == "hapmat" and not data.exists():
        if not HAPMAT.exists():
            return f"no {HAPMAT.name} beside the repository"
        import_hapmat(HAPMAT, data)
    elif name == "biotac":
        try:
            import h5py  # noqa: F401
        except ImportError:
            return "h5py is not installed (pip install '.[biotac]')"
        if not list(BIOTAC.glob("*.h5")):
            return "no BioTac .h5 files beside the repository"
        data = import_biotac_cached(cache)
    return data, load_dataset(data)


def run_dataset(name: str, data: Path, takes: list[Take], out: Path, seeds: tuple[int, ...],
                base: TrainConfig) -> dict:
    ours, base_runs = [], []
    for seed in seeds:
        cfg = base.replace(seed=seed, **SETTINGS[name])
        t0, c0 = time.perf_counter(), _cpu()
        m = train_module.train(data, out / f"{name}-seed{seed}", cfg, progress=False)
        m["wall_seconds"], m["cpu_seconds"] = time.perf_counter() - t0, _cpu() - c0
        b = band_logistic(takes, cfg)
        print(f"<!-- {name} seed {seed}: defaults {m['accuracy']:.3f} (val "
              f"{m['val_accuracy']:.3f}, best epoch {m['best_epoch'] + 1}, "
              f"{m['wall_seconds']:.0f} s wall, {m['cpu_seconds']:.0f} s CPU); baseline "
              f"{b['accuracy']:.3f} (val {b['val_accuracy']:.3f}, C={b['C']:g}, "
              f"{b['cpu_seconds']:.1f} s CPU) -->", flush=True)
        ours.append(m)
        base_runs.append(b)
    return {"ours": ours, "baseline": base_runs}


def _each(runs: list[dict]) -> str:
    return ", ".join(f"{r['accuracy']:.3f}" for r in runs)


def _stat(runs: list[dict], key: str = "accuracy") -> str:
    v = np.array([r[key] for r in runs])
    return f"{v.mean():.3f} +/- {v.std():.3f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for datasets and runs")
    p.add_argument("--only", choices=DATASETS, action="append", help="one dataset (repeatable)")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    p.add_argument("--cache", type=Path, default=CACHE,
                   help=f"folder for the imported BioTac takes (default {CACHE})")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change a default for every run (as tactile-train --set)")
    args = p.parse_args(argv)
    seeds = tuple(int(s) for s in args.seeds.split(",") if s.strip())
    base = train_module.parse_sets(args.set, TrainConfig(threads=1))
    results = {}
    for name in args.only or DATASETS:
        got = prepare(name, args.out, args.cache)
        if isinstance(got, str):
            print(f"<!-- {name}: skipped, {got} -->", flush=True)
            continue
        results[name] = run_dataset(name, *got, args.out, seeds, base)
    print(f"\n| dataset | windows train/val/test | defaults: test accuracy (seed "
          f"{', '.join(map(str, seeds))}) | mean +/- sd | baseline: test accuracy | "
          "mean +/- sd | defaults - baseline | validation: defaults / baseline | "
          "defaults per run: wall / CPU |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        ours, bl = r["ours"], r["baseline"]
        w = ours[0]["split_windows"]
        gap = np.mean([o["accuracy"] for o in ours]) - np.mean([b["accuracy"] for b in bl])
        print(f"| {name} | {w['train']}/{w['val']}/{w['test']} | "
              f"{_each(ours)} | {_stat(ours)} | {_each(bl)} | {_stat(bl)} | "
              f"{gap:+.3f} | {_stat(ours, 'val_accuracy')} / {_stat(bl, 'val_accuracy')} | "
              f"{np.mean([o['wall_seconds'] for o in ours]):.0f} s / "
              f"{np.mean([o['cpu_seconds'] for o in ours]):.0f} s |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
