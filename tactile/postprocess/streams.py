"""Label streams made of pieces of takes, neighbours of different classes (for measuring and
calibrating the post-processing).

A take is one surface from start to end, so its label stream has no true change; a user of the
pen moves from one surface to another. This module makes sample streams that do: each gap-free
run of a take's samples is cut into pieces of at most ``dwell_s`` seconds (:func:`run_pieces`),
the pieces of one group (a user) are put in a seeded random order in which neighbours differ in
class wherever that is possible (:func:`order`), and joined sample by sample into one
:class:`SampleStream` with the true class of every sample (:func:`join`, :func:`make_streams`).

The caller then runs the model over each joined stream as a pen would (the runtime's
:class:`~tactile.runtime.stream.Stream` at export and in ``bench/label_stream.py``, PyTorch in
``tactile-eval``): consecutive samples, no gap, so a window slides across the boundary of two
pieces (part of one surface, part of the next) and a carried state carries on across it, as on
the pen. :func:`window_ends` gives the windows the model makes, and :func:`window_stream` turns
the model's probabilities into a :class:`~tactile.postprocess.metrics.WindowStream`: a window's
time is its last sample's (sample ``i`` at ``i / rate_hz`` s) and its truth is its last
sample's class. Why the last sample's: it is the surface under the pen when the label is
reported, so a window still mostly of the old surface counts against the new one, and the
latency from a true change runs from the first window that ends on the new surface (at most one
hop after the surface changed) to the change event; the time the window needs to fill with the
new surface is part of that latency, as it is for a user.

numpy only, no file I/O (the callers read the takes and run the model).
"""

from __future__ import annotations

import math
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
    """Consecutive samples of one take, no gap among them: ``label`` the true class index,
    ``values`` (n, C) float32 in the model's channel order and units, n >= 1."""

    label: int
    values: np.ndarray


@dataclass(frozen=True)
class SampleStream:
    """Pieces joined sample by sample: ``values`` (N, C) float32, ``truth`` (N,) the class
    index of every sample, ``classes`` the class names, ``rate_hz`` the sample rate (sample
    ``i`` at ``i / rate_hz`` s)."""

    values: np.ndarray
    truth: np.ndarray
    classes: tuple[str, ...]
    rate_hz: float


def run_pieces(label: int, values: np.ndarray, rate_hz: float,
               dwell_s: float = DWELL_S) -> list[Piece]:
    """One gap-free run of a take's samples (``values`` (n, C), at ``rate_hz``) cut into pieces
    of at most ``dwell_s`` s (``floor(dwell_s * rate_hz)`` samples, at least 1) from the run's
    first sample; the last piece holds the rest."""
    if not dwell_s > 0:
        raise ConfigError(f"dwell {dwell_s!r} s: must be > 0")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"rate {rate_hz!r} Hz: must be a finite number > 0")
    values = np.asarray(values, np.float32)
    if values.ndim != 2:
        raise ConfigError(f"samples of shape {values.shape}: expected (n, channels)")
    size = max(1, math.floor(dwell_s * rate_hz + 1e-9))
    return [Piece(int(label), values[a:a + size]) for a in range(0, len(values), size)]


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


def join(pieces: list[Piece], classes: tuple[str, ...] | list[str],
         rate_hz: float) -> SampleStream:
    """``pieces`` one after the other, sample by sample, as one stream with no gap."""
    if not pieces:
        raise ConfigError("join: no pieces")
    widths = {p.values.shape[1] for p in pieces}
    if len(widths) != 1:
        raise ConfigError(f"join: pieces of {sorted(widths)} channels")
    truth = np.concatenate([np.full(len(p.values), p.label, np.int64) for p in pieces])
    return SampleStream(np.concatenate([p.values for p in pieces]).astype(np.float32), truth,
                        tuple(classes), float(rate_hz))


def make_streams(groups: dict[str, list[Piece]], classes: tuple[str, ...] | list[str],
                 rate_hz: float, seed: int = 0) -> list[SampleStream]:
    """One stream per group (e.g. a user; in sorted name order) that has pieces: its pieces in
    the order :func:`order` draws with a generator seeded by ``seed`` and the group's name (a
    group's order does not depend on the other groups)."""
    out = []
    for name in sorted(groups):
        if groups[name]:
            rng = np.random.default_rng([seed, sum(map(ord, name))])
            out.append(join(order(groups[name], rng), classes, rate_hz))
    return out


def window_ends(n: int, window: int, hop: int) -> np.ndarray:
    """Index of the last sample of each window a pen makes on ``n`` consecutive samples (the
    first window's samples 0..window-1, then one every ``hop``): (M,) int64, empty when
    ``n < window``."""
    if window < 1 or hop < 1:
        raise ConfigError(f"window {window} and hop {hop} must be >= 1")
    return np.arange(window - 1, n, hop, dtype=np.int64)


def window_stream(stream: SampleStream, probs: np.ndarray, window: int,
                  hop: int) -> WindowStream:
    """The model's probabilities ``probs`` (M, classes) of the windows of :func:`window_ends`
    on ``stream``, as a :class:`WindowStream`: each window's time is its last sample's (s),
    its truth its last sample's class."""
    ends = window_ends(len(stream.truth), window, hop)
    probs = np.asarray(probs, np.float64)
    if not len(ends) or len(probs) != len(ends):
        raise ConfigError(f"{len(probs)} windows' probabilities for a stream of "
                          f"{len(stream.truth)} samples that makes {len(ends)} windows of "
                          f"{window} samples every {hop}")
    return WindowStream(ends / stream.rate_hz, stream.truth[ends], probs, stream.classes)


def shortfall(streams: list[WindowStream], min_minutes: float = MIN_MINUTES) -> str | None:
    """Why ``streams`` are too little to calibrate on (less than ``min_minutes`` in all, or no
    true change between two classes in any of them), or None when they are enough."""
    minutes = sum(s.minutes for s in streams)
    if minutes < min_minutes:
        return f"{minutes:.2f} min of validation stream, less than {min_minutes:g}"
    if not any((np.diff(s.truth) != 0).any() for s in streams):
        return "no validation stream holds two classes (no change to measure)"
    return None


__all__ = ["DWELL_S", "MIN_MINUTES", "Piece", "SampleStream", "join", "make_streams", "order",
           "run_pieces", "shortfall", "window_ends", "window_stream"]
