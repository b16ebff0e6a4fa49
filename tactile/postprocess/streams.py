"""Label streams made of pieces of takes, neighbours of different classes (for measuring and
calibrating the post-processing).

A take is one surface from start to end, so its label stream has no true change; a user of the
pen moves from one surface to another. This module makes streams that do: each take's windows
(their times, true class and the model's probabilities, however they were computed: the
runtime's :class:`~tactile.runtime.stream.Stream` at export and in ``bench/label_stream.py``,
PyTorch in ``tactile-eval``) are cut into pieces of at most ``dwell_s`` seconds
(:func:`run_pieces`), the pieces of one group (a user) are put in a seeded random order in which
neighbours differ in class wherever that is possible, and played one after the other as one
:class:`~tactile.postprocess.metrics.WindowStream` (:func:`join`, :func:`make_streams`).

The windows of a piece are those the model gave inside one take; a window that would straddle
two pieces (part of one surface, part of the next) does not exist here, and the state of a
carried model restarts at each take. numpy only, no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tactile.errors import ConfigError
from tactile.postprocess.metrics import WindowStream

DWELL_S = 30.0
"""Seconds per piece: a surface is touched for this long before the next one."""
MIN_MINUTES = 1.0
"""Least validation stream, min, worth calibrating on (about four pieces at :data:`DWELL_S`)."""


@dataclass(frozen=True)
class Piece:
    """Consecutive windows of one take: ``label`` the true class index, ``t`` (n,) window
    times in s (non-decreasing), ``probs`` (n, classes) the model's probabilities (0..1)."""

    label: int
    t: np.ndarray
    probs: np.ndarray


def run_pieces(label: int, t: np.ndarray, probs: np.ndarray,
               dwell_s: float = DWELL_S) -> list[Piece]:
    """One gap-free run of a take's windows (``t`` (n,) s, ``probs`` (n, classes)) cut into
    pieces of at most ``dwell_s`` s, by window time from the run's first window; every piece
    has at least one window."""
    if not dwell_s > 0:
        raise ConfigError(f"dwell {dwell_s!r} s: must be > 0")
    t = np.asarray(t, np.float64).reshape(-1)
    probs = np.asarray(probs, np.float64)
    if probs.ndim != 2 or len(probs) != len(t):
        raise ConfigError(f"{len(t)} window times and probabilities of shape {probs.shape}")
    if not len(t):
        return []
    slot = np.floor((t - t[0]) / dwell_s).astype(np.int64)
    bounds = [0, *(np.flatnonzero(np.diff(slot)) + 1).tolist(), len(t)]
    return [Piece(int(label), t[a:b], probs[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


def order(pieces: list, rng: np.random.Generator, label=lambda p: p.label) -> list:
    """A random order of ``pieces`` in which consecutive ones differ in class (``label`` of a
    piece) wherever that is possible."""
    left, out, prev = list(pieces), [], None
    while left:
        other = [i for i, p in enumerate(left) if label(p) != prev] or list(range(len(left)))
        i = other[int(rng.integers(len(other)))]
        out.append(left.pop(i))
        prev = label(out[-1])
    return out


def join(pieces: list[Piece], classes: tuple[str, ...] | list[str], hop_s: float) -> WindowStream:
    """``pieces`` played one after the other: each piece's times shifted so that its first
    window comes ``hop_s`` s after the previous piece's last (one hop of the model)."""
    if not pieces:
        raise ConfigError("join: no pieces")
    ts, offset = [], 0.0
    for p in pieces:
        shifted = p.t - p.t[0] + offset
        ts.append(shifted)
        offset = float(shifted[-1]) + hop_s
    truth = np.concatenate([np.full(len(p.t), p.label, np.int64) for p in pieces])
    return WindowStream(np.concatenate(ts), truth, np.concatenate([p.probs for p in pieces]),
                        tuple(classes))


def make_streams(groups: dict[str, list[Piece]], classes: tuple[str, ...] | list[str],
                 hop_s: float, seed: int = 0) -> list[WindowStream]:
    """One stream per group (e.g. a user; in sorted name order) that has pieces: its pieces in
    the order :func:`order` draws with a generator seeded by ``seed`` and the group's name (a
    group's order does not depend on the other groups)."""
    out = []
    for name in sorted(groups):
        if groups[name]:
            rng = np.random.default_rng([seed, sum(map(ord, name))])
            out.append(join(order(groups[name], rng), classes, hop_s))
    return out


def shortfall(streams: list[WindowStream], min_minutes: float = MIN_MINUTES) -> str | None:
    """Why ``streams`` are too little to calibrate on (less than ``min_minutes`` in all, or no
    true change between two classes in any of them), or None when they are enough."""
    minutes = sum(s.minutes for s in streams)
    if minutes < min_minutes:
        return f"{minutes:.2f} min of validation stream, less than {min_minutes:g}"
    if not any((np.diff(s.truth) != 0).any() for s in streams):
        return "no validation stream holds two classes (no change to measure)"
    return None


__all__ = ["DWELL_S", "MIN_MINUTES", "Piece", "join", "make_streams", "order", "run_pieces",
           "shortfall"]
