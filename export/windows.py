"""Windows to measure parity on: the run's test split, else a simulated pen, else random data.

Every source gives :class:`Probe`: windows (N, window, C) float32 in the channels' units, their
labels when known, and runs of consecutive windows (for carried state), ordered in time. A probe
larger than the budget is thinned to a stratified, seeded sample: every class in turn, every take
of a class in turn, blocks of consecutive windows from a seeded position in each take.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tactile.device.protocol import PEN_CHANNELS
from tactile.device.sim import TEXTURES, PenSimulator
from tactile.training.data import cut, model_data, ordered_signals

CARRY_STEPS = 24
"""Consecutive windows per simulated or random run (the contract asks for >= 20)."""
SEED = 20240607
"""Seed of the simulated and random windows (fixed: the same figures on every export)."""


@dataclass
class Probe:
    """x (N, T, C) float32 in units; y (N,) class index or None; runs: index arrays in order;
    take: (N,) the take (or simulated stream) each window comes from, None if unknown."""

    x: np.ndarray
    y: np.ndarray | None
    runs: list[np.ndarray]
    source: str
    take: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.x)


def probe_windows(ck: dict, data: Path | None = None, max_windows: int = 256) -> Probe:
    """Windows for checkpoint ``ck``: from ``data`` if given, else simulated or random; at
    most ``max_windows``, a stratified sample (:func:`stratified`) when there are more."""
    if data is not None:
        probe = from_dataset(ck, Path(data))
    elif set(ck["channels"]) <= {c.name for c in PEN_CHANNELS}:
        probe = simulated(ck)
    else:
        probe = random_windows(ck)
    block = CARRY_STEPS if ck["config"].get("state") == "carry" else 1
    return stratified(probe, max_windows, block)


def from_dataset(ck: dict, data: Path, signals=None) -> Probe:
    """The run's test rows of ``data`` when its takes are the run's (by content), else every
    take of it (:func:`~tactile.training.data.model_data`, as ``tactile-eval`` reads them).
    ``signals``: the ones the model reads in time order (default: its config's)."""
    cfg = ck["config"]
    takes, rows, source, _ = model_data(
        ck, data, data.name, ordered_signals(cfg) if signals is None else signals)
    w = cut(takes, tuple(ck["classes"]), tuple(ck["channels"]), cfg["window"], cfg["hop"], rows)
    order = np.lexsort((w.start, w.run))
    bounds = np.flatnonzero(np.diff(w.run[order])) + 1
    return Probe(w.x, w.y, np.split(order, bounds), source, w.take)


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
    take = np.repeat(np.arange(len(ck["classes"])), CARRY_STEPS)
    return Probe(np.concatenate(xs), y if (y >= 0).all() else None, runs, "simulated pen", take)


def random_windows(ck: dict, n_runs: int = 4) -> Probe:
    """Gaussian windows scaled like the training data (its per-channel mean and std)."""
    cfg = ck["config"]
    rng = np.random.default_rng(SEED)
    mean, std = np.asarray(ck["mean"]), np.asarray(ck["std"])
    n = n_runs * CARRY_STEPS
    x = (rng.standard_normal((n, cfg["window"], len(mean))) * std + mean).astype(np.float32)
    runs = [np.arange(CARRY_STEPS) + k * CARRY_STEPS for k in range(n_runs)]
    take = np.repeat(np.arange(n_runs), CARRY_STEPS)
    return Probe(x, None, runs, "random, scaled like the training data", take)


def stratified(p: Probe, max_windows: int, block: int = 1, seed: int = SEED) -> Probe:
    """At most ``max_windows`` windows of ``p``, spread over its classes and takes.

    Classes take turns (in class order), and within a class its takes take turns (in a seeded
    order); each turn adds ``block`` consecutive windows of the take, continuing from where its
    last turn stopped, the first from a seeded position among its windows (in run and time
    order; a block that reaches the end of a run goes on in the take's next run, wrapping
    around). With ``block`` = :data:`CARRY_STEPS` (carried state) the runs stay long, unless
    that would leave classes out: the block shrinks to ``max_windows // classes``. The same
    probe and seed give the same windows. ``p.source`` gains how many classes and takes the
    sample covers.
    """
    if len(p) <= max_windows:
        return p
    rng = np.random.default_rng(seed)
    take = p.take if p.take is not None else np.zeros(len(p), np.int64)
    y = p.y if p.y is not None else np.zeros(len(p), np.int64)
    order = np.concatenate(p.runs)  # every window, run after run, in time order
    run_of = np.empty(len(p), np.int64)
    for k, r in enumerate(p.runs):
        run_of[r] = k
    # Per (class, take): its windows in run and time order, and where the next turn starts.
    cursors: dict[int, list] = {}
    for key_class in np.unique(y[order]):
        in_class = order[y[order] == key_class]
        takes = np.unique(take[in_class])
        rng.shuffle(takes)
        cursors[int(key_class)] = [[in_class[take[in_class] == t], None] for t in takes]
    block = max(1, min(block, max_windows // len(cursors)))
    picked: list[int] = []
    chosen: set[int] = set()
    turn = {c: 0 for c in cursors}
    while len(picked) < max_windows:
        progress = False
        for c, entries in cursors.items():
            if len(picked) >= max_windows:
                break
            for _ in range(len(entries)):  # the class's next take that has windows left
                rows, at = entries[turn[c] % len(entries)]
                turn[c] += 1
                if at is None:
                    at = int(rng.integers(len(rows)))
                n = min(block, max_windows - len(picked), len(rows))
                new = [int(rows[(at + i) % len(rows)]) for i in range(n)]
                new = [r for r in new if r not in chosen]
                entries[(turn[c] - 1) % len(entries)][1] = (at + n) % len(rows)
                if new:
                    picked += new
                    chosen.update(new)
                    progress = True
                    break
        if not progress:
            break
    rows = np.array(picked)
    # Runs: the picked windows of each original run, split where they stop being consecutive.
    position = np.empty(len(p), np.int64)
    position[order] = np.arange(len(order))
    keep = rows[np.lexsort((position[rows],))]
    cut_at = np.flatnonzero((np.diff(run_of[keep]) != 0) | (np.diff(position[keep]) != 1)) + 1
    new_runs = np.split(np.arange(len(keep)), cut_at)
    n_classes = len(np.unique(y[keep])) if p.y is not None else None
    n_takes = len(np.unique(take[keep]))
    covers = f"{n_classes} classes, {n_takes} takes" if n_classes is not None else (
        f"{n_takes} streams")
    return Probe(p.x[keep], None if p.y is None else p.y[keep], new_runs,
                 f"{p.source}; stratified sample over {covers}",
                 None if p.take is None else p.take[keep])
