"""How good a label stream is against the truth: accuracy, stability, false changes, latency.

A :class:`WindowStream` is what the runtime saw on one stream (window times, the model's
probabilities) with the true class of every window, e.g. takes of different classes played one
after the other. :func:`raw_track` and :func:`smoothed_track` turn it into the labels and change
events a user would get (the raw argmax, or a
:class:`~tactile.postprocess.smoothing.PostProcessor`), and :func:`figures` measures them;
:func:`compare` gives the raw and smoothed figures side by side.

Definitions (:func:`figures`), over all windows of all streams:

* ``accuracy``: share of windows whose reported label is the true class (an ``uncertain``
  window counts as wrong); ``stable_accuracy``: the same over the windows with a stable label
  only (None when there is none); ``uncertain``: share of windows with no stable label. For the
  raw stream every window is stable, so the first two are equal and the third is 0.
* true changes: the start of each stream (from nothing to its first window's class) and every
  window whose true class differs from the previous window's. A true change's interval runs
  from its window to the next true change (or the stream's end); its time is its window's time.
* events: the raw stream's are its label changes, its first window included (from nothing);
  the smoothed stream's are the post-processor's change events (the first after a reset
  included). An event is *true* when it is the first event in a true change's interval whose
  ``to`` is the interval's true class; every other event is *false* (a flicker, a wrong class,
  a second announcement). A true change is *detected* by its true event, latency = the event's
  time - the change's time (s), or, when no event is needed because the stream's current label
  (the last event's ``to``) already is the new class when the change happens, with latency 0;
  otherwise it is *missed* (counted, no latency).
* ``false_per_min``: false events per minute of stream; a stream lasts from its first window's
  time to its last's plus one median window spacing (each window stands for one hop).
* ``latency_median_s``, ``latency_p95_s``: over the detected changes (numpy's linear
  percentile; None when none was detected).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tactile.errors import ConfigError
from tactile.postprocess.smoothing import PostProcessor, SmoothingSettings, check_classes


@dataclass(frozen=True)
class WindowStream:
    """One stream of windows and its truth.

    ``t`` (N,) window times in s (each window's last sample), non-decreasing; ``truth`` (N,)
    true class indices into ``classes``; ``probs`` (N, classes) the model's probabilities
    (0..1). One stream is one run of the post-processor: it is reset at its start only.
    """

    t: np.ndarray
    truth: np.ndarray
    probs: np.ndarray
    classes: tuple[str, ...]

    def __post_init__(self) -> None:
        t = np.asarray(self.t, np.float64).reshape(-1)
        truth = np.asarray(self.truth).reshape(-1)
        probs = np.asarray(self.probs, np.float64)
        classes = check_classes(self.classes)
        n, k = len(t), len(classes)
        if n < 1 or probs.shape != (n, k) or truth.shape != (n,):
            raise ConfigError(f"a stream of {n} windows needs truth ({n},) and probs ({n}, {k}); "
                              f"got {truth.shape} and {probs.shape}")
        if not np.issubdtype(truth.dtype, np.integer) or truth.min() < 0 or truth.max() >= k:
            raise ConfigError(f"truth: class indices 0..{k - 1}")
        if not np.isfinite(t).all() or (np.diff(t) < 0).any():
            raise ConfigError("t: finite window times in s, non-decreasing")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "truth", truth.astype(np.int64))
        object.__setattr__(self, "probs", probs)
        object.__setattr__(self, "classes", classes)

    @property
    def minutes(self) -> float:
        """The stream's length: first to last window time plus one median spacing, min."""
        dt = float(np.median(np.diff(self.t))) if len(self.t) > 1 else 0.0
        return (self.t[-1] - self.t[0] + dt) / 60.0


@dataclass(frozen=True)
class Track:
    """The labels a user gets on one stream: ``labels`` (N,) class indices, -1 for
    ``uncertain``; ``events`` (window index, class index it changes to), in order."""

    labels: np.ndarray
    events: list[tuple[int, int]]


def raw_track(stream: WindowStream) -> Track:
    """The raw stream: each window's argmax (ties to the lowest index); an event at its first
    window and at every window whose label differs from the previous one's."""
    labels = stream.probs.argmax(1)
    changes = [0, *(np.flatnonzero(np.diff(labels) != 0) + 1).tolist()]
    return Track(labels, [(i, int(labels[i])) for i in changes])


def smoothed_track(stream: WindowStream, settings: SmoothingSettings) -> Track:
    """The stream through a fresh :class:`PostProcessor` with ``settings`` (window index as
    seq): the stable label or -1, and its change events."""
    post = PostProcessor(settings, stream.classes)
    index = {c: k for k, c in enumerate(stream.classes)}
    labels = np.full(len(stream.t), -1, np.int64)
    events = []
    for i, (p, t) in enumerate(zip(stream.probs, stream.t)):
        out = post.update(p, float(t), i)
        if out.stable:
            labels[i] = index[out.label]
        if out.event is not None:
            events.append((i, index[out.event["to"]]))
    return Track(labels, events)


def _changes(stream: WindowStream, track: Track) -> tuple[int, list[float], int, int]:
    """(true changes, latencies of the detected ones in s, missed, false events)."""
    truth, t = stream.truth, stream.t
    starts = [0, *(np.flatnonzero(np.diff(truth) != 0) + 1).tolist()]
    ends = [*starts[1:], len(truth)]
    true_events: set[int] = set()  # positions in track.events
    latencies, missed = [], 0
    e = 0  # first event at or after the current interval's start
    for a, b in zip(starts, ends):
        while e < len(track.events) and track.events[e][0] < a:
            e += 1
        current = track.events[e - 1][1] if e > 0 else None  # the label when the change happens
        if current == truth[a]:
            latencies.append(0.0)
            continue
        for j in range(e, len(track.events)):
            i, to = track.events[j]
            if i >= b:
                missed += 1
                break
            if to == truth[a]:
                true_events.add(j)
                latencies.append(float(t[i] - t[a]))
                break
        else:
            missed += 1
    return len(starts), latencies, missed, len(track.events) - len(true_events)


def figures(streams: list[WindowStream], tracks: list[Track]) -> dict:
    """The figures of the module's docstring for ``tracks`` (one per stream, in order): a dict
    of ``windows``, ``minutes``, ``accuracy``, ``stable_accuracy``, ``uncertain`` (shares 0..1),
    ``changes`` (true), ``detected``, ``missed``, ``events``, ``false_changes``,
    ``false_per_min``, ``latency_median_s``, ``latency_p95_s``."""
    if len(streams) != len(tracks) or not streams:
        raise ConfigError(f"{len(streams)} streams and {len(tracks)} tracks: need one track per "
                          "stream, at least one")
    labels = np.concatenate([tr.labels for tr in tracks])
    truth = np.concatenate([s.truth for s in streams])
    stable = labels >= 0
    changes, lat, missed, false, events = 0, [], 0, 0, 0
    for s, tr in zip(streams, tracks):
        c, la, m, f = _changes(s, tr)
        changes, missed, false, events = changes + c, missed + m, false + f, events + len(tr.events)
        lat += la
    minutes = sum(s.minutes for s in streams)
    return {
        "windows": int(len(labels)),
        "minutes": minutes,
        "accuracy": float((labels == truth).mean()),
        "stable_accuracy": float((labels[stable] == truth[stable]).mean()) if stable.any()
        else None,
        "uncertain": float((~stable).mean()),
        "changes": changes,
        "detected": len(lat),
        "missed": missed,
        "events": events,
        "false_changes": false,
        "false_per_min": false / minutes if minutes > 0 else None,
        "latency_median_s": float(np.percentile(lat, 50)) if lat else None,
        "latency_p95_s": float(np.percentile(lat, 95)) if lat else None,
    }


def compare(streams: list[WindowStream], settings: SmoothingSettings) -> dict:
    """``{"raw": figures, "smoothed": figures}`` of the same streams (:func:`figures`)."""
    return {"raw": figures(streams, [raw_track(s) for s in streams]),
            "smoothed": figures(streams, [smoothed_track(s, settings) for s in streams])}


__all__ = ["Track", "WindowStream", "compare", "figures", "raw_track", "smoothed_track"]
