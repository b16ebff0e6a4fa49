"""A run's label stream in PyTorch: raw against post-processed, on streams made of its takes.

``tactile-eval`` measures what a user of the exported model would see: the run's test takes cut
into pieces of 30 s and played one after the other, neighbours of different classes
(:mod:`tactile.postprocess.streams`), the raw argmax against the post-processed stable label
(:mod:`tactile.postprocess.metrics`). The post-processing setting is the one
:func:`~tactile.postprocess.calibration.calibrate` picks on the run's validation takes played
the same way, with this checkpoint's own probabilities (the same takes and rule as
``tactile-export --data``, which replays them through the exported file instead), or a setting
given by the caller.

The run's validation takes are not in its checkpoint: :func:`validation_rows` draws the run's
split again from its config on the dataset and uses it only when it gives the test takes the run
recorded, matched by content.
"""

from __future__ import annotations

import numpy as np

from tactile.errors import ConfigError
from tactile.postprocess.calibration import calibrate
from tactile.postprocess.metrics import compare
from tactile.postprocess.smoothing import SmoothingSettings
from tactile.postprocess.streams import DWELL_S, Piece, make_streams, run_pieces, shortfall
from tactile.training.data import Windows, cut, find_test_split, split_takes

FALLBACK = SmoothingSettings(n=5, p_min=0.6, hold=2)
"""The setting measured when none is given and the validation takes cannot calibrate one (the
runtime documentation's example)."""


def validation_rows(takes: list, ck: dict, cfg, folder: str
                    ) -> tuple[dict[int, tuple[int, int]] | None, str]:
    """The run's validation rows of ``takes`` (every take of the dataset ``folder``, in the
    order :func:`~tactile.device.recordings.load_dataset` gives), ``{take index: (first,
    end)}``, and ``""``; or None and why not (one phrase): the dataset's takes are not the
    run's (its test takes not found by content), or the split drawn again from ``cfg`` (the
    checkpoint's config) gives other test takes than the run recorded."""
    test, _, verified = find_test_split(takes, ck.get("test_rows"), ck.get("test_fingerprints"),
                                        folder)
    if not verified:
        return None, f"{folder} does not hold the run's test takes (matched by content)"
    try:
        split = split_takes(takes, cfg)
    except ConfigError as e:
        return None, f"the run's split cannot be drawn again on {folder} ({e})"
    if split.test != test:
        return None, f"the run's split drawn again on {folder} gives other test takes"
    if not split.val:
        return None, "the run has no validation takes"
    return split.val, ""


def group_of(take) -> str:
    """A take's stream: its ``user`` (``-`` for takes that name none)."""
    return str(take.meta.get("user", "-"))


def pieces(w: Windows, probs: np.ndarray, takes: list, window: int, rate_hz: float,
           dwell_s: float = DWELL_S) -> dict[str, list[Piece]]:
    """``{group: pieces}`` of windows ``w`` with their probabilities ``probs`` (N, classes):
    each gap-free run cut into pieces of ``dwell_s`` s; a window's time is its last sample's
    (row / ``rate_hz``, s), as the runtime stamps it."""
    groups: dict[str, list[Piece]] = {}
    order = np.lexsort((w.start, w.run))  # each gap-free run's windows in time order
    for rows in np.split(order, np.flatnonzero(np.diff(w.run[order])) + 1):
        t = (w.start[rows] + window - 1) / rate_hz
        take = takes[int(w.take[rows[0]])]
        groups.setdefault(group_of(take), []).extend(
            run_pieces(int(w.y[rows[0]]), t, probs[rows], dwell_s))
    return groups


def stream_figures(model, ck: dict, takes: list, folder: str, test: Windows,
                   test_probs: np.ndarray, predict, settings: SmoothingSettings | None = None,
                   seed: int = 0) -> dict:
    """The label stream figures of the test windows ``test`` (their probabilities
    ``test_probs``): ``{"setting", "source", "calibration" (what it saw on validation, or None),
    "streams", "dwell_s", "raw", "smoothed"}`` (``raw`` and ``smoothed`` as
    :func:`~tactile.postprocess.metrics.figures`). ``predict(windows)``: the model's
    probabilities (N, classes) of windows (:func:`tactile.training.evaluate.predict`).
    ``settings`` None: calibrated on the run's validation takes of ``takes``
    (:func:`validation_rows`), else :data:`FALLBACK`, saying why."""
    cfg = model.cfg
    classes, rate = tuple(ck["classes"]), float(ck["sample_rate_hz"])
    hop_s = cfg.hop / rate
    calibration, source = None, "given"
    if settings is None:
        rows, why = validation_rows(takes, ck, cfg, folder)
        streams = []
        if rows is not None:
            w = cut(takes, classes, tuple(ck["channels"]), cfg.window, cfg.hop, rows)
            streams = make_streams(pieces(w, predict(w), takes, cfg.window, rate),
                                   classes, hop_s, seed)
            why = shortfall(streams) or ""
        if why:
            settings, source = FALLBACK, f"not calibrated: {why}"
        else:
            cal = calibrate(streams)
            settings, calibration = cal.settings, cal.figures
            n = len(streams)
            source = (f"calibrated on the run's validation takes: {n} stream"
                      f"{'s' if n != 1 else ''}, {sum(s.minutes for s in streams):.1f} min")
    test_streams = make_streams(pieces(test, test_probs, takes, cfg.window, rate), classes,
                                hop_s, seed)
    return {"setting": settings.describe(), "source": source, "calibration": calibration,
            "streams": len(test_streams), "dwell_s": DWELL_S,
            **compare(test_streams, settings)}


ROWS = (("accuracy (uncertain counts wrong)", "accuracy", True),
        ("stable-label accuracy", "stable_accuracy", True),
        ("windows uncertain", "uncertain", True),
        ("false changes per minute", "false_per_min", False),
        ("true changes (incl. stream starts)", "changes", False),
        ("missed changes", "missed", False),
        ("change latency median, s", "latency_median_s", False),
        ("change latency p95, s", "latency_p95_s", False))


def stream_table(f: dict) -> str:
    """The figures of :func:`stream_figures` as text: the setting, then raw and post-processed
    side by side."""
    def fmt(v, pct: bool) -> str:
        if v is None:
            return "-"
        return f"{v * 100:.1f} %" if pct else f"{v:.2f}" if isinstance(v, float) else str(v)

    lines = [f"label stream: {f['streams']} streams of the test takes in pieces of "
             f"{f['dwell_s']:g} s, {f['raw']['minutes']:.1f} min; post-processed with "
             f"{f['setting']} ({f['source']})",
             f"  {'':36s}{'raw':>10s}{'post-processed':>16s}"]
    for name, key, pct in ROWS:
        lines.append(f"  {name:36s}{fmt(f['raw'][key], pct):>10s}"
                     f"{fmt(f['smoothed'][key], pct):>16s}")
    return "\n".join(lines)


__all__ = ["FALLBACK", "group_of", "pieces", "stream_figures", "stream_table",
           "validation_rows"]
