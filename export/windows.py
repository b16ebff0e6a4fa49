"""Windows to measure parity on: the run's test split, else a simulated pen, else random data.

Every source gives :class:`Probe`: windows (N, window, C) float32 in the channels' units, their
labels when known, and runs of consecutive windows (for carried state), ordered in time.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tactile.device.info import PEN_CHANNELS
from tactile.device.recording import load_dataset
from tactile.device.simulator import TEXTURES, PenSimulator
from tactile.errors import RecordingError
from tactile.training.data import cut

CARRY_STEPS = 24
"""Consecutive windows per simulated or random run (the contract asks for >= 20)."""
SEED = 20240607
"""Seed of the simulated and random windows (fixed: the same figures on every export)."""


@dataclass
class Probe:
    """x (N, T, C) float32 in units; y (N,) class index or None; runs: index arrays in order."""

    x: np.ndarray
    y: np.ndarray | None
    runs: list[np.ndarray]
    source: str

    def __len__(self) -> int:
        return len(self.x)


def probe_windows(ck: dict, data: Path | None = None, max_windows: int = 256) -> Probe:
    """Windows for checkpoint ``ck``: from ``data`` if given, else simulated or random."""
    if data is not None:
        probe = from_dataset(ck, Path(data))
    elif set(ck["channels"]) <= {c.name for c in PEN_CHANNELS}:
        probe = simulated(ck)
    else:
        probe = random_windows(ck)
    return _thin(probe, max_windows)


def from_dataset(ck: dict, data: Path) -> Probe:
    """The run's test rows of ``data`` when its takes are the run's, else every take of it."""
    cfg = ck["config"]
    classes = tuple(ck["classes"])
    takes = [t for t in load_dataset(data) if t.label in classes]
    if not takes:
        raise RecordingError(f"{data}: no take is labelled with one of {list(classes)}")
    names = [t.path.name for t in takes]
    test = ck.get("test_rows", {})
    if test and all(n in names for n in test):
        rows = {names.index(n): tuple(r) for n, r in test.items()}
        source = f"test split of {data.name} ({len(rows)} takes)"
    else:
        rows = None
        source = f"every take of {data.name} ({len(takes)} takes)"
    w = cut(takes, classes, tuple(ck["channels"]), cfg["window"], cfg["hop"], rows)
    order = np.lexsort((w.start, w.run))
    bounds = np.flatnonzero(np.diff(w.run[order])) + 1
    return Probe(w.x, w.y, np.split(order, bounds), source)


def simulated(ck: dict) -> Probe:
    """Consecutive windows of the simulated pen drawing each class (when it is a texture)."""
    cfg = ck["config"]
    window, hop = cfg["window"], cfg["hop"]
    names = [c.name for c in PEN_CHANNELS]
    idx = [names.index(c) for c in ck["channels"]]
    n = (CARRY_STEPS - 1) * hop + window
    xs, ys, runs = [], [], []
    for k, label in enumerate(ck["classes"]):
        texture = label if label in TEXTURES else "paper"
        sim = PenSimulator(texture, seed=SEED + k, rate_hz=float(ck["sample_rate_hz"]))
        scale = np.array([c.scale for c in sim.info.channels])
        offset = np.array([c.offset for c in sim.info.channels])
        values = (sim.read(n) * scale + offset)[:, idx].astype(np.float32)  # (n, C)
        starts = np.arange(CARRY_STEPS) * hop
        xs.append(values[starts[:, None] + np.arange(window)[None, :]])  # (S, T, C)
        ys.append(np.full(CARRY_STEPS, k) if label in TEXTURES else np.full(CARRY_STEPS, -1))
        runs.append(np.arange(CARRY_STEPS) + k * CARRY_STEPS)
    y = np.concatenate(ys)
    return Probe(np.concatenate(xs), y if (y >= 0).all() else None, runs, "simulated pen")


def random_windows(ck: dict, n_runs: int = 4) -> Probe:
    """Gaussian windows scaled like the training data (its per-channel mean and std)."""
    cfg = ck["config"]
    rng = np.random.default_rng(SEED)
    mean, std = np.asarray(ck["mean"]), np.asarray(ck["std"])
    n = n_runs * CARRY_STEPS
    x = (rng.standard_normal((n, cfg["window"], len(mean))) * std + mean).astype(np.float32)
    runs = [np.arange(CARRY_STEPS) + k * CARRY_STEPS for k in range(n_runs)]
    return Probe(x, None, runs, "random, scaled like the training data")


def _thin(p: Probe, max_windows: int) -> Probe:
    """At most ``max_windows`` windows: the first windows of every run (at least
    :data:`CARRY_STEPS` of each, while the budget lasts), so classes stay mixed and carried
    runs stay long."""
    if len(p) <= max_windows:
        return p
    share = max(CARRY_STEPS, max_windows // len(p.runs))
    keep, total = [], 0
    for r in p.runs:
        r = r[: min(share, max_windows - total)]
        if len(r):
            keep.append(r)
            total += len(r)
    rows = np.concatenate(keep)
    new_runs, at = [], 0
    for r in keep:
        new_runs.append(np.arange(at, at + len(r)))
        at += len(r)
    return Probe(p.x[rows], None if p.y is None else p.y[rows], new_runs, p.source)
