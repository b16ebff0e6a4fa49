"""Datasets as windows: cut recordings into windows, split them without leaks, normalise.

No window spans a recorded gap (windows are cut inside :meth:`Take.segments`), no take (or
user) gives windows to two splits, and normalisation statistics come from training windows only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tactile.device.recording import Take
from tactile.errors import ConfigError
from tactile.training.config import TrainConfig


@dataclass
class Windows:
    """Windows of one split.

    x: (N, window, C) float32 values in the channels' units; y: (N,) class index;
    take: (N,) index of the take each window came from; start: (N,) first row in that take;
    run: (N,) id of the gap-free run (segment) the window lies in, for carried-state runs.
    """

    x: np.ndarray
    y: np.ndarray
    take: np.ndarray
    start: np.ndarray
    run: np.ndarray

    def __len__(self) -> int:
        return len(self.y)

    def subset(self, mask: np.ndarray) -> Windows:
        w = self
        return Windows(w.x[mask], w.y[mask], w.take[mask], w.start[mask], w.run[mask])


def concat(a: Windows, b: Windows) -> Windows:
    """The windows of ``a`` then ``b``; ``b``'s run ids are moved past ``a``'s."""
    run = b.run + (int(a.run.max()) + 1 if len(a) else 0)
    return Windows(*(np.concatenate([u, v]) for u, v in (
        (a.x, b.x), (a.y, b.y), (a.take, b.take), (a.start, b.start), (a.run, run))))


def classes_of(takes: list[Take]) -> tuple[str, ...]:
    return tuple(sorted({t.label for t in takes}))


def channel_index(take: Take, channels: tuple[str, ...]) -> list[int]:
    if not channels:
        return list(range(len(take.channels)))
    missing = [c for c in channels if c not in take.channels]
    if missing:
        raise ConfigError(f"channels {missing} not in the recordings' {list(take.channels)}")
    return [take.channels.index(c) for c in channels]


def cut(
    takes: list[Take],
    classes: tuple[str, ...],
    channels: tuple[str, ...],
    window: int,
    hop: int,
    rows: dict[int, tuple[int, int]] | None = None,
    shift: int = 0,
) -> Windows:
    """Windows from ``takes`` (optionally only rows [a, b) of take i: ``rows[i]``).

    ``shift`` moves every window start by that many samples (the robustness check's shifted
    windows); windows that would leave their segment are not made.
    """
    xs, ys, tk, st, rn = [], [], [], [], []
    run_id = 0
    for i, take in enumerate(takes):
        if rows is not None and i not in rows:
            continue
        lo, hi = rows[i] if rows is not None else (0, len(take.seq))
        values = take.values()[:, channel_index(take, channels)].astype(np.float32)
        y = classes.index(take.label)
        for a, b in take.segments():
            a, b = max(a, lo), min(b, hi)
            starts = np.arange(a, b - window + 1, hop) + shift
            starts = starts[(starts >= a) & (starts + window <= b)]
            if len(starts):
                idx = starts[:, None] + np.arange(window)[None, :]
                xs.append(values[idx])
                ys.append(np.full(len(starts), y))
                tk.append(np.full(len(starts), i))
                st.append(starts)
                rn.append(np.full(len(starts), run_id))
            run_id += 1
    if not xs:
        raise ConfigError(f"no window of {window} samples fits in the selected recordings")
    return Windows(
        np.concatenate(xs), np.concatenate(ys), np.concatenate(tk), np.concatenate(st),
        np.concatenate(rn),
    )


def groups_of(takes: list[Take], split: str) -> np.ndarray:
    """(n_takes,) group id: the user (when takes say so) or the take itself."""
    if split == "user" and all("user" in t.meta for t in takes):
        users = sorted({str(t.meta["user"]) for t in takes})
        return np.array([users.index(str(t.meta["user"])) for t in takes])
    return np.arange(len(takes))


@dataclass
class Split:
    train: dict[int, tuple[int, int]]
    val: dict[int, tuple[int, int]]
    test: dict[int, tuple[int, int]]
    description: str


def split_takes(takes: list[Take], cfg: TrainConfig) -> Split:
    """Assign takes (or row ranges of takes) to train / validation / test, deterministically."""
    rng = np.random.default_rng(cfg.seed)
    if cfg.split == "time":
        train, val, test = {}, {}, {}
        for i, t in enumerate(takes):
            n = len(t.seq)
            cut_test = int(round(n * (1 - cfg.test_fraction)))
            cut_val = int(round(cut_test * (1 - cfg.val_fraction)))
            train[i], val[i], test[i] = (0, cut_val), (cut_val, cut_test), (cut_test, n)
        return Split(train, val, test, f"time: first {1 - cfg.test_fraction:.0%} of each take "
                     f"trains (last {cfg.val_fraction:.0%} of it validates), the rest tests")
    groups = groups_of(takes, cfg.split)
    ids = rng.permutation(np.unique(groups))
    n_test = max(1, int(round(len(ids) * cfg.test_fraction)))
    n_val = max(1, int(round((len(ids) - n_test) * cfg.val_fraction)))
    if len(ids) - n_test - n_val < 1:
        raise ConfigError(
            f"{len(ids)} {cfg.split}s cannot be split into train, validation and test: record "
            "more takes or use split='time'"
        )
    test_ids, val_ids = set(ids[:n_test]), set(ids[n_test : n_test + n_val])
    whole = {i: (0, len(t.seq)) for i, t in enumerate(takes)}
    pick = {
        name: {i: r for i, r in whole.items() if sel(groups[i])}
        for name, sel in (
            ("test", lambda g: g in test_ids),
            ("val", lambda g: g in val_ids),
            ("train", lambda g: g not in test_ids and g not in val_ids),
        )
    }
    return Split(pick["train"], pick["val"], pick["test"],
                 f"{cfg.split}: test {sorted(int(g) for g in test_ids)}, "
                 f"validation {sorted(int(g) for g in val_ids)}, train the other "
                 f"{len(ids) - n_test - n_val}")


def channel_stats(w: Windows) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and std (C,) over training windows; a constant channel gets std 1."""
    flat = w.x.reshape(-1, w.x.shape[-1]).astype(np.float64)
    mean, std = flat.mean(0), flat.std(0)
    std[std < 1e-8] = 1.0
    return mean.astype(np.float32), std.astype(np.float32)
