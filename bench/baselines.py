"""The default model against a band-energy logistic regression, on the same windows, per dataset
and seed; prints one markdown table (mean and spread over the seeds) for docs/results.md.

    python bench/baselines.py --out runs/baselines                  # 4 datasets x seeds 0, 1, 2
    python bench/baselines.py --out runs/baselines --only small --seeds 0
    python bench/baselines.py --out runs/nested --nested   # refit off / on, validation as test
    python bench/baselines.py --out runs/mine --data data/mine --seeds 0   # your own takes

Exit status: 0 when the table is printed, 1 for a bad argument or setting (one line, before
any dataset is made) or a dataset training refuses (a ``--data`` folder it cannot split: one
line), 2 when every dataset asked for is skipped (each says why) or when a run
or baseline in OUT was made with other settings (it says which; finished runs and baselines
are reused, so other settings need another OUT), 130 on Ctrl-C (finished runs are kept).

Datasets (``--only``, repeatable):

* ``small``: ``tactile-sim --dataset D --takes 6`` (7 textures x 6 simulated users x 60 s), the
  default split by user (3 users train, 1 validates, 2 test).
* ``readme``: the README's set (24 users x 5 textures x 60 s) with the README's ``hop=25``.
* ``hapmat``: the HapMat stick IMU (``tactile-import-hapmat``), ``split=time``.
* ``biotac``: the BioTac BOLT recordings (5 objects, 74 trials, two fingers) as a user gets them:
  ``tactile-import-biotac ../shared/datasets/biotac-bolt/*.h5 --out CACHE`` (done once, into
  ``--cache``, outside the repository), then trained on that folder: pressure, vibration and
  electrodes (:data:`BIOTAC_CHANNELS`, 84 of the importer's 88: not the two temperatures of
  each finger; the takes declare each finger's vibration a 2.2 kHz signal, which the default
  model frames at that rate), one take per trial, split by trial: the fifth
  repetition of every object and pressure tests (``test = "repetition:5"``), one of the other
  four validates (drawn from the seed); ``hop=50`` (windows do not overlap): a run takes about
  120-330 s of CPU; the default hop (``--set hop=10``: 5x the windows) took 185-285 s a run
  without the refit, against about 150 s at ``hop=50``, and about 4 GB of memory.
  Needs the ``[biotac]`` extra (h5py); skipped, saying why, without it or the files.

``--nested`` judges ``refit`` without test data: per dataset and seed the validation takes (with
``split=time`` the validation block of every take) stand in for the test, an inner validation is
drawn from the training takes as the bench draws validation (the last ``val_fraction`` of the
training block), and the defaults train with ``refit=off`` and ``refit=on`` on that (runs and
their data folders in ``OUT/nested/``). The folders these runs read hold no test take (links to
the training and validation takes; with ``split=time`` copies cut before the test block).

The baseline: per window and channel the mean, the log standard deviation and the log energy of
the mean-free, Hann-tapered window in :data:`N_BANDS` equal bands from 0 Hz to the Nyquist
frequency; standardised on the training windows; scikit-learn's multinomial
``LogisticRegression``, its ``C`` picked from :data:`CS` on the validation windows (and, when
the defaults refit on training + validation windows, refitted on them too): fitted once per
split in a command (seeds whose split is the same, e.g. with the test and validation takes
named, and ``--reinit``'s pass, which names each seed's split, share it; each keeps its own
file). For takes that declare high-rate signals a second one adds each signal's log band energies
at its true rate (:func:`signal_features`), ``C`` also chosen on validation. The defaults train
with ``tactile.training.train.train`` and one thread; each run's wall time and its CPU time
(user + sys of this process) are printed. Beside the window accuracy, the table gives both
models' majority vote per test take (``tactile-eval``'s ``per_take``), what trial-based datasets
report.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from tactile.cli import Parser
from tactile.device.protocol import Gap
from tactile.device.recordings import Take, TakeWriter, import_hapmat, load_dataset
from tactile.device.sim import TEXTURES, make_dataset
from tactile.errors import ConfigError, TactileError
from tactile.training import loop
from tactile.training import train as train_module
from tactile.training.checkpoint import SAVED_BEFORE
from tactile.training.config import TrainConfig
from tactile.training.data import classes_of, pick_channels, split_takes, split_windows
from tactile.training.evaluate import per_take
from tactile.training.modality import signals_of_takes
from tactile.training.overrides import parse_sets
from tactile.training.run_files import libraries_line

SHARED = Path(__file__).resolve().parents[2] / "shared" / "datasets"
HAPMAT = SHARED / "hapmat" / "hapmat_stick_imu.npz"
BIOTAC = SHARED / "biotac-bolt"
README_TEXTURES = ("non_contact", "paper", "nonwoven_cloth", "plastic_folder", "mouse_pad")
DATASETS = ("small", "readme", "hapmat", "biotac")
N_BANDS = 5
CS = (0.01, 0.1, 1.0, 10.0)
# BioTac's vibration, pressure and electrode channels (per finger 22 + 1 + 19, in the
# importer's order), without the two temperatures
BIOTAC_CHANNELS = tuple(f"f{k}_{name}" for k in (0, 1) for name in (
    *(f"pac_{i:02d}" for i in range(22)), "pdc", *(f"ele_{i:02d}" for i in range(19))))
# the data settings of each dataset (everything else: the defaults)
SETTINGS = {"small": {}, "readme": {"hop": 25}, "hapmat": {"split": "time"},
            "biotac": {"hop": 50, "test": "repetition:5", "channels": BIOTAC_CHANNELS}}
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "tactile-bench"


def dataset_settings(name: str, given: frozenset[str] = frozenset()) -> dict:
    """The data settings of dataset ``name`` (:data:`SETTINGS`; a ``--data`` folder has none)
    but those the command line gives itself (``given``: keys of ``--set`` or a candidate's
    settings, which win)."""
    return {k: v for k, v in SETTINGS.get(name, {}).items() if k not in given}


def _keys(pairs: list[str]) -> frozenset[str]:
    return frozenset(p.partition("=")[0] for p in pairs)


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


def signal_features(x: np.ndarray, signals: list[list[int]], rate: float) -> np.ndarray:
    """(N, T, C) windows -> (N, S * nb): per high-rate signal (the indices of its ``r``
    sub-sample channels, in time order) the log energy of the mean-free, Hann-tapered window
    of the signal at its true rate (``T * r`` samples at ``rate * r`` Hz) in the model's
    third-octave bands up to its Nyquist frequency
    (:func:`tactile.training.frontend.band_bins`)."""
    from tactile.training.frontend import band_bins

    out = []
    for idx in signals:
        s = x[:, :, idx].astype(np.float64).reshape(len(x), -1)  # (N, T * r)
        s = s - s.mean(axis=1, keepdims=True)
        power = np.abs(np.fft.rfft(s * np.hanning(s.shape[1])[None], axis=1)) ** 2
        out += [np.log(power[:, a:b].sum(axis=1) + 1e-12) for a, b in band_bins(power.shape[1])]
    return np.stack(out, axis=1) if out else np.zeros((len(x), 0))


def band_logistic(takes: list[Take], cfg: TrainConfig) -> dict:
    """The baseline on the windows ``cfg`` gives the default model: accuracies and timings.
    For takes that declare high-rate signals among the channels, ``high_rate`` holds the same
    figures for the logistic regression on the window features plus each signal's bands
    (:func:`signal_features`), its ``C`` also chosen on the validation windows."""
    t0, c0 = time.perf_counter(), _cpu()
    classes = classes_of(takes)
    channels = pick_channels(takes[0], cfg.channels)
    rate = takes[0].info.sample_rate_hz
    _, parts = split_windows(takes, classes, channels, cfg)
    feats = {k: window_features(w.x, rate) for k, w in parts.items()}
    out = _logistic(feats, parts, classes, takes, cfg)
    signals = [[channels.index(c) for c in names]
               for _, names in signals_of_takes(takes, channels)]
    if signals:
        t1, c1 = time.perf_counter(), _cpu()
        both = {k: np.concatenate([f, signal_features(parts[k].x, signals, rate)], axis=1)
                for k, f in feats.items()}
        out["high_rate"] = {**_logistic(both, parts, classes, takes, cfg),
                            "wall_seconds": time.perf_counter() - t1,
                            "cpu_seconds": _cpu() - c1}
    else:
        out["high_rate"] = None
    return {**out, "split_windows": {k: len(w) for k, w in parts.items()},
            "wall_seconds": time.perf_counter() - t0, "cpu_seconds": _cpu() - c0}


def _logistic(feats: dict, parts: dict, classes: tuple[str, ...], takes: list[Take],
              cfg: TrainConfig) -> dict:
    """A logistic regression on ``feats`` (part -> (N, F)), standardised on the training
    windows, ``C`` from :data:`CS` chosen on the validation windows: its test figures."""
    from sklearn.linear_model import LogisticRegression
    from threadpoolctl import threadpool_limits

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
    probs = np.zeros((len(y["test"]), len(classes)))
    probs[:, model.classes_] = model.predict_proba(x["test"])
    take = per_take(parts["test"], probs, [t.path.stem for t in takes])
    return {"accuracy": float((probs.argmax(1) == y["test"]).mean()),
            "take_accuracy": take["take_accuracy"], "val_accuracy": val_acc[best_c], "C": best_c}


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
    cmd = [sys.executable, "-m", "tactile.device.commands.import_biotac",
           *map(str, sorted(BIOTAC.glob("*.h5"))), "--out", str(part)]
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
            return f"no {HAPMAT.name} in {HAPMAT.parent}"
        import_hapmat(HAPMAT, data)
    elif name == "biotac":
        try:
            import h5py  # noqa: F401
        except ImportError:
            return "h5py is not installed (pip install '.[biotac]')"
        if not list(BIOTAC.glob("*.h5")):
            return f"no BioTac .h5 files in {BIOTAC}"
        data = import_biotac_cached(cache)
    return data, load_dataset(data)


class ValidationRecorder:
    """Inside ``with``: keeps the probabilities of every epoch's validation (what
    :func:`tactile.training.loop.validate` predicts), to judge selection rules afterwards
    (:func:`selection_rules`). The first windows predicted are the validation split's; later
    calls on the same windows are later epochs; any other windows (the test split) are not
    kept."""

    def __init__(self) -> None:
        self.val, self.probs = None, []

    def __enter__(self) -> ValidationRecorder:
        self._predict = loop.predict

        def predict(model, w, *a, **kw):
            probs = self._predict(model, w, *a, **kw)
            if self.val is None:
                self.val = w
            if w is self.val:
                self.probs.append(probs)
            return probs

        loop.predict = predict
        return self

    def __exit__(self, *exc) -> None:
        loop.predict = self._predict

    def save(self, path: Path) -> None:
        w = self.val
        np.savez_compressed(path, probs=np.stack(self.probs), y=w.y, take=w.take, start=w.start)


def _halves(take: np.ndarray, start: np.ndarray) -> np.ndarray:
    """True for the windows in the first half (by start) of their take's validation windows."""
    first = np.zeros(len(take), bool)
    for t in np.unique(take):
        rows = np.flatnonzero(take == t)
        first[rows[np.argsort(start[rows], kind="stable")[: len(rows) // 2]]] = True
    return first


RULES = ("loss", "accuracy")


def pick_epoch(rule: str, acc: np.ndarray, loss: np.ndarray, patience: int) -> int:
    """The epoch (0-based) that ``select=rule`` with ``patience`` keeps, given the curves
    (the run stops ``patience`` epochs after the last improvement, or at the curves' end);
    the same comparisons as :func:`tactile.training.loop.improves`."""
    s = {"best": np.inf, "best_acc": -1.0}
    best, stale = 0, 0
    for e in range(len(acc)):
        if loop.improves(rule, float(acc[e]), float(loss[e]), s["best"], s["best_acc"]):
            s["best"], s["best_acc"], best, stale = float(loss[e]), float(acc[e]), e, 0
        else:
            stale += 1
            if stale >= patience:
                break
    return best


def selection_rules(path: Path, patience: int) -> dict:
    """Each rule judged on held-out validation windows: the rule picks its epoch on the first
    half (in time) of every validation take and is scored on the second half, and the other
    way round; the mean of the two accuracies, and the epochs picked on the whole."""
    d = np.load(path)
    probs, y = d["probs"], d["y"]
    hit = probs.argmax(2) == y[None]  # (epochs, N)
    nll = -np.log(probs[:, np.arange(len(y)), y] + 1e-9)
    first = _halves(d["take"], d["start"])
    out = {}
    for rule in RULES:
        scores = []
        for pick, score in ((first, ~first), (~first, first)):
            e = pick_epoch(rule, hit[:, pick].mean(1), nll[:, pick].mean(1), patience)
            scores.append(float(hit[e, score].mean()))
        e_all = pick_epoch(rule, hit.mean(1), nll.mean(1), patience)
        out[rule] = {"held_out": float(np.mean(scores)), "epoch": e_all + 1,
                     "val_accuracy": float(hit[e_all].mean())}
    return out


def run_dataset(name: str, data: Path, takes: list[Take], out: Path, seeds: tuple[int, ...],
                base: TrainConfig, curves: bool = False, label: str = "defaults",
                baselines: Path | None = None, reinit: int = 0,
                given: frozenset[str] = frozenset(), fitted: dict | None = None) -> dict:
    """The defaults (``base``) and the baseline on every seed. A run this script finished in
    its folder is read, not trained again (so is a stored baseline); one made with other
    settings is a :class:`StaleRun` (:func:`finished`, :func:`cached_baseline`). ``reinit``:
    each seed's split trained with seed ``seed + reinit`` (:func:`same_split`). ``given``: the
    settings the command line gave (:func:`dataset_settings`). ``fitted``: the baselines fitted
    so far, by :func:`split_key` (one the seed does not change is fitted once; shared by the
    calls of one command)."""
    ours, base_runs = [], []
    by_split = {} if fitted is None else fitted
    for seed in seeds:
        cfg = base.replace(seed=seed, **dataset_settings(name, given))
        if reinit:
            cfg = same_split(takes, cfg, seed + reinit)
        run = out / f"{name}-seed{seed}"
        m = finished(run, cfg)
        if m is None:
            t0, c0 = time.perf_counter(), _cpu()
            with ValidationRecorder() as rec:
                m = train_module.train(data, run, cfg, progress=False)
            m = _timed(run, m, t0, c0, cfg)
            if curves:
                rec.save(run / "val-curves.npz")
        if curves and (run / "val-curves.npz").exists():
            # the rules with the default patience (a recording run may wait longer)
            m["rules"] = selection_rules(run / "val-curves.npz", TrainConfig.patience)
        key = split_key(takes, cfg)
        b = cached_baseline((baselines or out / "baseline") / f"{name}-seed{seed}.json", cfg,
                            lambda c=cfg, k=key, s=seed: by_split.get(k) or {
                                **band_logistic(takes, c), "split_seed": s})
        by_split.setdefault(key, {"split_seed": seed, **{
            k: v for k, v in b.items() if k != "settings"}})
        rules = "".join(f"; select={r}: held-out val {v['held_out']:.3f}, epoch {v['epoch']}, "
                        f"val {v['val_accuracy']:.3f}" for r, v in m.get("rules", {}).items())
        print(f"<!-- {name} seed {seed}: {label} {m['accuracy']:.3f} (val "
              f"{m['val_accuracy']:.3f}, best epoch {m['best_epoch'] + 1}, "
              f"{m['wall_seconds']:.0f} s wall, {m['cpu_seconds']:.0f} s CPU{rules}); baseline "
              f"{b['accuracy']:.3f} (val {b['val_accuracy']:.3f}, C={b['C']:g}, "
              f"{_baseline_cost(b, seed)}){_high_rate_note(b)} -->", flush=True)
        ours.append(m)
        base_runs.append(b)
    return {"ours": ours, "baseline": base_runs}


def split_key(takes: list[Take], cfg: TrainConfig) -> str:
    """What a baseline depends on: the windows of each part (the split's takes and rows) and
    the data settings but the seed, which draws the split only where ``test``/``val`` leave it
    to chance (named repetitions, ``split=time``: every seed's split is the same)."""
    try:
        split = split_takes(takes, cfg)
    except ConfigError:  # training says what is wrong with the split: its own key per seed
        return json.dumps(_data_settings(cfg))
    settings = {k: v for k, v in _data_settings(cfg).items() if k not in ("seed", "test", "val")}
    return json.dumps([settings, *(sorted(part.items()) for part in (
        split.train, split.val, split.test))])


def _baseline_cost(b: dict, seed: int) -> str:
    """The baseline's CPU time, or the seed whose identical split computed it."""
    first = b.get("split_seed", seed)
    return (f"{b['cpu_seconds']:.1f} s CPU" if first == seed else
            f"the same split as seed {first}: computed once")


def _high_rate_note(b: dict) -> str:
    h = b.get("high_rate")
    return (f"; with the high-rate bands {h['accuracy']:.3f} (val {h['val_accuracy']:.3f}, "
            f"C={h['C']:g})" if h else "")


class StaleRun(Exception):
    """A run or baseline in OUT made with other settings than this call's."""


# the settings a baseline depends on (its windows, its split, whether it refits)
DATA_KEYS = ("window", "hop", "channels", "split", "test", "val", "test_fraction",
             "val_fraction", "seed")


def _settings(cfg: TrainConfig) -> dict:
    return json.loads(json.dumps(cfg.to_dict()))


def _data_settings(cfg: TrainConfig) -> dict:
    d = _settings(cfg)
    return {**{k: d[k] for k in DATA_KEYS}, "refits": cfg.refits}


def _check_same(path: Path, kept: dict | None, want: dict) -> None:
    """StaleRun when ``kept`` (the settings stored with a result; None: stored before settings
    were) differs from ``want``."""
    if kept is None or kept == want:
        return
    diff = ", ".join(f"{k} {kept.get(k)!r} -> {want.get(k)!r}"
                     for k in sorted(set(kept) | set(want)) if kept.get(k) != want.get(k))
    raise StaleRun(f"{path}: made with other settings ({diff}): give another --out")


def finished(run: Path, cfg: TrainConfig | None = None) -> dict | None:
    """The metrics of a run this script finished (its ``metrics.json`` with the script's CPU
    and wall times, not interrupted), else None: a run stopped half-way (Ctrl-C, or the script
    ended between the training and its times) is trained again. A finished run made with other
    settings than ``cfg`` is a :class:`StaleRun`."""
    try:
        m = json.loads((run / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    if "cpu_seconds" not in m or m.get("interrupted"):
        return None
    if cfg is not None:
        kept = m.get("bench_settings")
        if isinstance(kept, dict):  # keys that came later: what their absence meant
            kept = {**_settings(TrainConfig()), **SAVED_BEFORE, **kept}
        _check_same(run, kept, _settings(cfg))
    return m


def _timed(run: Path, m: dict, t0: float, c0: float, cfg: TrainConfig | None = None) -> dict:
    """A finished training's metrics with its times (and ``cfg``'s settings), written back;
    Ctrl-C ends the script."""
    if m.get("interrupted"):
        raise KeyboardInterrupt
    m["wall_seconds"], m["cpu_seconds"] = time.perf_counter() - t0, _cpu() - c0
    if cfg is not None:
        m["bench_settings"] = _settings(cfg)
    (run / "metrics.json").write_text(json.dumps(m, indent=1) + "\n")
    return m


def cached_baseline(bfile: Path, cfg: TrainConfig, compute) -> dict:
    """The baseline stored in ``bfile``, else ``compute()`` stored there with the settings it
    depends on; one stored with other such settings is a :class:`StaleRun`."""
    want = _data_settings(cfg)
    if bfile.exists():
        b = json.loads(bfile.read_text())
        _check_same(bfile, b.get("settings"), want)
        if "take_accuracy" in b:  # else stored before the vote per take was: computed again
            return b
    b = {**compute(), "settings": want}
    bfile.parent.mkdir(parents=True, exist_ok=True)
    bfile.write_text(json.dumps(b, indent=1) + "\n")
    return b


def _literal(name: str) -> str:
    """A ``name:`` selector value that matches exactly ``name`` (shell patterns escaped, never
    read as a range of numbers)."""
    if "," in name:
        raise ValueError(f"take {name!r}: a comma cannot be named in a selector")
    out = "".join(f"[{c}]" if c in "[]*?" else c for c in name)
    if re.fullmatch(r"-?\d+--?\d+", name):  # "3-5" would be the range 3..5
        out = f"[{out[0]}]{out[1:]}"
    return out


# keys a take's JSON gets from its writer (the rest is copied to a cut copy of the take)
_WRITTEN = ("format", "version", "label", "started_utc", "source", "device", "columns", "samples",
            "first_seq", "last_seq", "gaps", "decoder", "complete")


def _write_head(take: Take, rows: int, folder: Path) -> None:
    """A copy of ``take``'s first ``rows`` rows (its gaps among them) in ``folder``."""
    extra = {k: v for k, v in take.meta.items() if k not in _WRITTEN}
    src = take.meta.get("source", "")
    with TakeWriter(folder, take.label, take.info, src, name=take.path.stem, extra=extra) as w:
        gaps = {g["row"]: g for g in take.meta.get("gaps", []) if g.get("row") is not None}
        for a, b in take.segments():
            if a >= rows:
                break
            if a in gaps and a > 0:
                g = gaps[a]
                w.gap(Gap(int(g["seq"]), int(g["missing"]), g["reason"]))
            b = min(b, rows)
            w.write(int(take.seq[a]), int(take.t_us[a]), take.raw[a:b])


def same_split(takes: list[Take], cfg: TrainConfig, seed: int) -> TrainConfig:
    """``cfg`` with another ``seed`` (the initial weights, the epochs' windows, the
    augmentation) and the same split: its test and validation takes named (``split=time`` does
    not depend on the seed)."""
    if cfg.split == "time":
        return cfg.replace(seed=seed)
    split = split_takes(takes, cfg)

    def names(part: dict) -> str:
        return "name:" + ",".join(_literal(takes[i].path.stem) for i in part)

    return cfg.replace(seed=seed, test=names(split.test), val=names(split.val))


def nested_data(takes: list[Take], cfg: TrainConfig, folder: Path) -> TrainConfig:
    """The nested split of ``cfg``'s: writes into ``folder`` (once; a folder that is there is
    whole) a dataset without ``cfg``'s test data, and returns the config whose test split is
    ``cfg``'s validation split and whose validation is drawn from ``cfg``'s training split.

    ``split=user``/``take``: links to the training and validation takes; the validation takes
    are named as the test (``test = "name:..."``) and the validation is drawn from the rest as
    ``split_takes`` draws it (``val_fraction`` of the users or takes, at least one).
    ``split=time``: each take cut before its test block; ``test_fraction = val_fraction``
    makes the test block the old validation block, and the last ``val_fraction`` of the rest
    validates."""
    split = split_takes(takes, cfg)
    if cfg.split == "time":
        ncfg = cfg.replace(test_fraction=cfg.val_fraction)
    else:
        stems = [takes[i].path.stem for i in split.val]
        ncfg = cfg.replace(test="name:" + ",".join(map(_literal, stems)), val="")
    if folder.exists():
        return ncfg
    part = folder.with_name(folder.name + ".partial")
    if part.exists():
        shutil.rmtree(part)
    part.mkdir(parents=True)
    for i, t in enumerate(takes):
        if cfg.split == "time":
            _write_head(t, split.val[i][1], part)
        elif i in split.train or i in split.val:
            for f in (t.path, t.path.with_suffix(".json")):
                (part / f.name).symlink_to(f.resolve())
    part.rename(folder)
    return ncfg


def run_nested(name: str, takes: list[Take], out: Path, seeds: tuple[int, ...],
               base: TrainConfig, given: frozenset[str] = frozenset()) -> list[dict]:
    """Per seed: the defaults with ``refit=off`` and ``refit=on`` (and the baseline without and
    with its refit) on the nested split (:func:`nested_data`), scored on its test split, the
    outer validation data. Runs already in ``out`` are read, not trained again."""
    rows = []
    for seed in seeds:
        cfg = base.replace(seed=seed, **dataset_settings(name, given))
        ncfg = nested_data(takes, cfg, out / f"data-{name}-seed{seed}")
        data = out / f"data-{name}-seed{seed}"
        row = {"dataset": name, "seed": seed}
        for refit in ("off", "on"):
            rcfg = ncfg.replace(refit=refit)
            run = out / f"{name}-seed{seed}-refit-{refit}"
            m = finished(run, rcfg)
            if m is None:
                t0, c0 = time.perf_counter(), _cpu()
                m = _timed(run, train_module.train(data, run, rcfg, progress=False), t0, c0,
                           rcfg)
            bfile = out / "baseline" / f"{name}-seed{seed}-refit-{refit}.json"
            b = cached_baseline(bfile, rcfg,
                                lambda c=rcfg, d=data: band_logistic(load_dataset(d), c))
            row[refit], row[f"baseline_{refit}"] = m, b
        print(f"<!-- nested {name} seed {seed}: proxy test refit off {row['off']['accuracy']:.3f}"
              f", on {row['on']['accuracy']:.3f} (inner val {row['off']['val_accuracy']:.3f}, "
              f"best epoch {row['off']['best_epoch'] + 1}, CPU {row['off']['cpu_seconds']:.0f} / "
              f"{row['on']['cpu_seconds']:.0f} s; {row['off']['split']}); baseline off "
              f"{row['baseline_off']['accuracy']:.3f}, on {row['baseline_on']['accuracy']:.3f} -->",
              flush=True)
        rows.append(row)
    return rows


def nested_table(rows: list[dict]) -> str:
    """Per dataset and seed the proxy-test accuracy with refit off and on, and per dataset the
    mean and spread of the paired differences."""
    lines = ["| dataset | seed | windows inner train/val, proxy test | inner validation | "
             "proxy test, refit off | refit on | on - off | baseline off / on |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w = r["off"]["split_windows"]
        lines.append(
            f"| {r['dataset']} | {r['seed']} | {w['train']}/{w['val']}, {w['test']} | "
            f"{r['off']['val_accuracy']:.3f} | {r['off']['accuracy']:.3f} | "
            f"{r['on']['accuracy']:.3f} | {r['on']['accuracy'] - r['off']['accuracy']:+.3f} | "
            f"{r['baseline_off']['accuracy']:.3f} / {r['baseline_on']['accuracy']:.3f} |")
    lines += ["", "| dataset | refit off (mean) | refit on (mean) | on - off: mean +/- sd "
              "(seeds) | baseline on - off |", "|---|---|---|---|---|"]
    for name in dict.fromkeys(r["dataset"] for r in rows):
        rs = [r for r in rows if r["dataset"] == name]
        off = np.array([r["off"]["accuracy"] for r in rs])
        on = np.array([r["on"]["accuracy"] for r in rs])
        boff = np.array([r["baseline_off"]["accuracy"] for r in rs])
        bon = np.array([r["baseline_on"]["accuracy"] for r in rs])
        lines.append(f"| {name} | {off.mean():.3f} | {on.mean():.3f} | {(on - off).mean():+.3f} "
                     f"+/- {(on - off).std():.3f} | {(bon - boff).mean():+.3f} |")
    return "\n".join(lines)


def _each(runs: list[dict], key: str = "accuracy") -> str:
    return ", ".join(f"{r[key]:.3f}" for r in runs)


def _stat(runs: list[dict], key: str = "accuracy") -> str:
    v = np.array([r[key] for r in runs])
    return f"{v.mean():.3f} +/- {v.std():.3f}"


def grid_table(grid: dict, seeds: tuple[int, ...]) -> str:
    """Validation accuracy of each candidate per dataset and seed (and the baseline's)."""
    names = list(next(iter(grid.values())))
    lines = ["| candidate | " + " | ".join(f"{n}: val (seed {', '.join(map(str, seeds))}), mean"
                                         for n in names) + " |",
             "|---" * (len(names) + 1) + "|"]

    def cell(runs: list[dict]) -> str:
        v = [r["val_accuracy"] for r in runs]
        return ", ".join(f"{a:.3f}" for a in v) + f"; **{np.mean(v):.3f}**"

    def rule(runs: list[dict], r: str, key: str) -> str:
        v = [run["rules"][r][key] for run in runs]
        return ", ".join(f"{a:.3f}" for a in v) + f"; **{np.mean(v):.3f}**"

    first = next(iter(grid.values()))
    lines.append("| baseline | " + " | ".join(cell(first[n]["baseline"]) for n in names) + " |")
    for label, res in grid.items():
        lines.append(f"| {label} | " + " | ".join(cell(res[n]["ours"]) for n in names) + " |")
        if all("rules" in run for n in names for run in res[n]["ours"]):
            for r in RULES:  # what each rule keeps with the default patience
                lines.append(f"| {label}, select={r} | " + " | ".join(
                    rule(res[n]["ours"], r, "val_accuracy") for n in names) + " |")
                lines.append(f"| {label}, select={r}, held-out halves | " + " | ".join(
                    rule(res[n]["ours"], r, "held_out") for n in names) + " |")
    return "\n".join(lines)


def _high_rate_cells(bl: list[dict]) -> str:
    """The table's three cells of the baseline with the high-rate bands ("-" without)."""
    hs = [b.get("high_rate") for b in bl]
    if not all(hs):
        return "- | - | -"
    return f"{_each(hs)} | {_stat(hs)} | {_each(hs, 'take_accuracy')}"


def main(argv: list[str] | None = None) -> int:
    """The command (:func:`_main`); a dataset or setting training refuses (a ``--data`` folder
    it cannot split, say) is its one line, exit 1."""
    try:
        return _main(argv)
    except TactileError as e:
        print(f"baselines.py: error: {e}", file=sys.stderr)
        return 1


def _main(argv: list[str] | None = None) -> int:
    p = Parser(prog="baselines.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for datasets and runs")
    p.add_argument("--only", choices=DATASETS, action="append", help="one dataset (repeatable)")
    p.add_argument("--data", type=Path, action="append", metavar="DIR",
                   help="your own dataset folder instead (repeatable; with --only as well): "
                        "the defaults against the baselines on it, with --set's settings only "
                        "(e.g. --set split=time for one take a class); its row is named by the "
                        "folder, its runs kept by the takes' content (OUT/takes-DIGEST/)")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    p.add_argument("--cache", type=Path, default=CACHE,
                   help=f"folder for the imported BioTac takes (default {CACHE})")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change a setting for every run (as tactile-train --set; it wins "
                        "over a dataset's own, such as BioTac's hop=50). Finished runs and "
                        "baselines in OUT are reused; one made with other settings stops the "
                        "script (exit 2): give other settings another OUT")
    p.add_argument("--candidate", action="append", nargs="+", metavar=("NAME", "KEY=VALUE"),
                   help="a grid of candidate defaults instead of the table: NAME and its "
                        "settings (repeatable; runs in OUT/NAME/, the baseline's in "
                        "OUT/baseline/); prints every candidate's validation accuracy per "
                        "dataset and seed")
    p.add_argument("--curves", action="store_true",
                   help="keep each run's validation probabilities per epoch (val-curves.npz) "
                        "and judge the selection rules (select=loss, accuracy) on held-out "
                        "halves of the validation takes")
    p.add_argument("--nested", action="store_true",
                   help="judge refit without test data: the validation takes as the test, an "
                        "inner validation drawn from the training takes, the defaults with "
                        "refit=off and refit=on (runs in OUT/nested/); prints their accuracy "
                        "on the validation takes per dataset and seed")
    p.add_argument("--reinit", type=int, default=0, metavar="K",
                   help="with --candidate: each candidate also trained with seed + K on each "
                        "seed's split (its test and validation takes named), runs in "
                        "OUT/NAME-reinitK/ (baselines in OUT/baseline-reinitK/): how far the "
                        "figures move with the initial weights, "
                        "the epochs' windows and the augmentation alone")
    args = p.parse_args(argv)
    try:
        seeds = tuple(int(s) for s in args.seeds.split(",") if s.strip())
    except ValueError:
        p.error(f"--seeds {args.seeds!r}: not comma-separated whole numbers")
    if not seeds:
        p.error("--seeds: give at least one seed")
    try:  # every setting checked before any dataset is made or imported
        base = parse_sets(args.set, TrainConfig(threads=1))
        candidates = [(label, parse_sets(sets, base), sets)
                      for label, *sets in args.candidate or []]
    except ConfigError as e:
        p.error(str(e))
    own = {}
    for folder in args.data or []:
        name = f"own-{re.sub(r'[^A-Za-z0-9_.-]', '_', folder.resolve().name)}"
        if not folder.is_dir():
            p.error(f"--data {folder}: not a folder")
        if name in own:
            p.error(f"--data {folder}: a second folder named {folder.resolve().name}")
        own[name] = folder
    print(libraries_line(), flush=True)
    data, where = {}, {}  # an own folder's runs by its takes' content: other takes, other runs
    for name, folder in own.items():  # first: a folder that cannot be read stops at once
        data[name] = folder, load_dataset(folder)
        digest = hashlib.sha256(" ".join(sorted(t.fingerprint() for t in data[name][1]))
                                .encode()).hexdigest()[:12]
        where[name] = args.out / f"takes-{digest}"
    for name in args.only or ([] if own else DATASETS):
        got = prepare(name, args.out, args.cache)
        if isinstance(got, str):
            print(f"<!-- {name}: skipped, {got} -->", flush=True)
            continue
        data[name] = got
    if not data:
        print("baselines.py: every dataset was skipped (the lines above, on stdout): nothing "
              "to run", file=sys.stderr)
        return 2
    if args.nested:
        rows = [r for name, (_, takes) in data.items()
                for r in run_nested(name, takes, args.out / "nested", seeds, base,
                                    _keys(args.set))]
        print(nested_table(rows))
        return 0
    fitted: dict = {}  # the baselines fitted, by split: each once in this command
    if args.candidate:
        grid = {}
        for label, cfg, sets in candidates:
            given = _keys(args.set) | _keys(sets)
            grid[label] = {name: run_dataset(name, *got, args.out / label, seeds, cfg,
                                             args.curves, label, args.out / "baseline",
                                             given=given, fitted=fitted)
                           for name, got in data.items()}
            if args.reinit:  # the same candidate and splits, other initial weights
                grid[f"{label}, seed + {args.reinit}"] = {
                    name: run_dataset(name, *got, args.out / f"{label}-reinit{args.reinit}",
                                      seeds, cfg, args.curves, f"{label} reinit",
                                      args.out / f"baseline-reinit{args.reinit}", args.reinit,
                                      given, fitted)
                    for name, got in data.items()}
        print(grid_table(grid, seeds))
        return 0
    results = {name: run_dataset(name, *got, where.get(name, args.out), seeds, base,
                                 args.curves, given=_keys(args.set), fitted=fitted)
               for name, got in data.items()}
    print(f"\n| dataset | windows train/val/test | defaults: test accuracy (seed "
          f"{', '.join(map(str, seeds))}) | mean +/- sd | baseline: test accuracy | "
          "mean +/- sd | defaults - baseline | validation: defaults / baseline | "
          "per take (majority vote): defaults / baseline | baseline + high-rate bands: test "
          "accuracy | mean +/- sd | its vote per take | defaults per run: wall / CPU |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        ours, bl = r["ours"], r["baseline"]
        w = ours[0]["split_windows"]
        gap = np.mean([o["accuracy"] for o in ours]) - np.mean([b["accuracy"] for b in bl])
        print(f"| {name} | {w['train']}/{w['val']}/{w['test']} | "
              f"{_each(ours)} | {_stat(ours)} | {_each(bl)} | {_stat(bl)} | "
              f"{gap:+.3f} | {_stat(ours, 'val_accuracy')} / {_stat(bl, 'val_accuracy')} | "
              f"{_each(ours, 'take_accuracy')} / {_each(bl, 'take_accuracy')} | "
              f"{_high_rate_cells(bl)} | {np.mean([o['wall_seconds'] for o in ours]):.0f} s / "
              f"{np.mean([o['cpu_seconds'] for o in ours]):.0f} s |")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        print("interrupted: finished runs are kept, the others train again next time",
              file=sys.stderr)
        sys.exit(130)
    except StaleRun as e:
        print(f"baselines.py: {e}", file=sys.stderr)
        sys.exit(2)
