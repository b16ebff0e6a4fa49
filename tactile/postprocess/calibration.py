"""Choosing the post-processing settings on validation streams (:func:`calibrate`).

Every setting of a small grid replays the same streams through a fresh
:class:`~tactile.postprocess.smoothing.PostProcessor` (:mod:`tactile.postprocess.metrics`), and
the rule of :func:`calibrate` picks one. What it saw goes with the setting into the model file
(:func:`~tactile.postprocess.smoothing.settings_to_metadata`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from tactile.errors import ConfigError
from tactile.postprocess.metrics import WindowStream, figures, raw_track, smoothed_track
from tactile.postprocess.smoothing import SmoothingSettings

MAX_FALSE_PER_MIN = 1.0
"""The change limit: at most one false change a minute (a user glancing at the label now and
then should rarely see it jump on an unchanged surface)."""


def default_grid() -> tuple[SmoothingSettings, ...]:
    """54 settings: moving averages of n in {1, 3, 5, 8} windows and exponential averages of
    tau in {0.5, 1.0} s, each with p_min in {0.5, 0.6, 0.7} and hold in {1, 2, 3}.

    Why these: at the pen's hop (25 samples at 100 Hz, 0.25 s) a moving average of n windows
    lags by about (n - 1) / 2 hops and an exponential one by about tau, so n 8 (0.9 s) and tau
    1 s are the longest averages that can still keep a median change latency under the issue's
    1 s; n 1 keeps the raw probabilities and lets p_min and hold alone do the work. p_min from
    0.5 (the leader then holds a majority of the probability, so no other class can) to 0.7
    (above it, with five classes, windows of the weaker classes spend long spells uncertain);
    hold of 1 to 3 windows (up to 0.75 s more latency at that hop). Small enough to replay
    minutes of validation streams in seconds on a board-class CPU.
    """
    averaging = [{"n": n, "tau": None} for n in (1, 3, 5, 8)] + \
        [{"n": None, "tau": tau} for tau in (0.5, 1.0)]
    return tuple(SmoothingSettings(**a, p_min=p, hold=h)
                 for a, p, h in itertools.product(averaging, (0.5, 0.6, 0.7), (1, 2, 3)))


@dataclass(frozen=True)
class Calibration:
    """The chosen ``settings``; ``figures`` it saw (JSON-able: the rule, the limit, whether the
    choice meets it, the raw stream's and the chosen setting's :func:`figures`); ``table``
    every setting of the grid with its figures, in grid order."""

    settings: SmoothingSettings
    figures: dict
    table: tuple[tuple[SmoothingSettings, dict], ...]


def _simplicity(s: SmoothingSettings) -> tuple:
    """Order among equally good settings: moving averages first (the simpler), then the
    shorter average, the shorter hold, the lower p_min (fewer windows uncertain)."""
    return (0 if s.n is not None else 1, s.n if s.n is not None else s.tau, s.hold, s.p_min)


def _key(s: SmoothingSettings, f: dict) -> tuple:
    """Best first: the largest share of windows that carry a correct stable label (an
    ``uncertain`` window counts as not correct), then the highest stable-label accuracy, then
    the shortest median latency, then :func:`_simplicity`."""
    stable = f["stable_accuracy"] if f["stable_accuracy"] is not None else -math.inf
    lat = f["latency_median_s"] if f["latency_median_s"] is not None else math.inf
    return (-f["accuracy"], -stable, lat, _simplicity(s))


def calibrate(streams: list[WindowStream], grid: tuple[SmoothingSettings, ...] | None = None,
              max_false_per_min: float = MAX_FALSE_PER_MIN,
              max_uncertain: float | None = None) -> Calibration:
    """Pick post-processing settings on validation ``streams`` (each replayed from a reset).

    Among the settings of ``grid`` (default :func:`default_grid`) with at most
    ``max_false_per_min`` false changes per minute (:mod:`~tactile.postprocess.metrics`), the
    one whose stream carries a correct stable label in the most windows (``accuracy``: an
    ``uncertain`` window is not a correct one); ties go to the highest stable-label accuracy,
    then the shortest median change latency, then the simplest setting (moving average before
    exponential, smaller n or tau, smaller hold, smaller p_min). If none meets the limits: the
    one with the fewest false changes per minute (ties broken the same way), and
    ``figures["met_limit"]`` is False.

    Why not the highest stable-label accuracy alone: it is measured over the stable windows
    only, so it favours the setting that leaves the most windows uncertain (the highest p_min
    and hold) whenever that setting is at all more accurate; on the shipped pen model's
    validation users it chose one that left a quarter of the test windows uncertain
    (``bench/label_stream.py``). ``max_uncertain`` (a share 0..1; None: no limit) also bounds
    the share of windows left uncertain.
    """
    if max_uncertain is not None and not 0.0 <= max_uncertain <= 1.0:
        raise ConfigError(f"max_uncertain {max_uncertain!r}: a share from 0 to 1, or None")
    grid = default_grid() if grid is None else tuple(grid)
    if not grid or not all(isinstance(s, SmoothingSettings) for s in grid):
        raise ConfigError("grid: one or more SmoothingSettings")
    if not streams or sum(st.minutes for st in streams) <= 0:
        raise ConfigError("calibrate: no validation streams, or none longer than one window")
    table = tuple((s, figures(streams, [smoothed_track(st, s) for st in streams])) for s in grid)
    ok = [(s, f) for s, f in table if f["false_per_min"] <= max_false_per_min
          and (max_uncertain is None or f["uncertain"] <= max_uncertain)]
    if ok:
        best, fig = min(ok, key=lambda sf: _key(*sf))
    else:
        best, fig = min(table, key=lambda sf: (sf[1]["false_per_min"], _key(*sf)))
    cap = "" if max_uncertain is None else f" and at most {max_uncertain:g} windows uncertain"
    seen = {
        "rule": f"most windows with a correct stable label, with at most "
                f"{max_false_per_min:g} false changes a minute{cap}; then the highest stable "
                f"accuracy, the shortest median latency, the simplest setting",
        "max_false_per_min": max_false_per_min,
        "max_uncertain": max_uncertain,
        "met_limit": bool(ok),
        "grid": len(grid),
        "streams": len(streams),
        "setting": best.describe(),
        "raw": _rounded(figures(streams, [raw_track(st) for st in streams])),
        "smoothed": _rounded(fig),
    }
    return Calibration(best, seen, table)


def _rounded(f: dict) -> dict:
    """Floats to 4 decimals, for metadata a person reads."""
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in f.items()}


MAX_UNCERTAIN = 0.5
"""The share of windows a file's default setting may leave ``uncertain``: a stream uncertain
more than half the time says less than it hides."""


def refusal(cal: Calibration) -> str | None:
    """Why a calibration's setting should not become a file's defaults (one phrase), or None.

    A setting that meets the limits (:func:`calibrate` with ``max_uncertain``
    :data:`MAX_UNCERTAIN`) is kept even when it labels fewer windows right than the raw stream:
    its price for a stream that changes at most once a minute on an unchanged surface is the
    windows it leaves ``uncertain``, which its figures say. One that does not (no setting of
    the grid gets there: the one with the fewest false changes) is kept only when it labels at
    least as many windows right as the raw stream."""
    f = cal.figures
    raw, chosen = f["raw"]["accuracy"], f["smoothed"]["accuracy"]
    if f["met_limit"] or chosen >= raw:
        return None
    cap = "" if f["max_uncertain"] is None else \
        f" with at most {f['max_uncertain']:.0%} of the windows uncertain"
    return (f"no setting of the grid gets to at most {f['max_false_per_min']:g} false change a "
            f"minute{cap}, and the one with the fewest, {cal.settings.describe()}, gives "
            f"fewer correct stable labels than the raw stream ({chosen:.1%} against {raw:.1%})")


LABELLED_BY, FIRST_TRAINING = "labelled_by", "first_training"
"""A calibration's figures say ``labelled_by: first_training`` when the validation streams were
labelled by a refit run's first model (the final one trained on them)."""
HELD_OUT = "labelled by the first training's model (the final one refit on them)"


def summary_line(f: dict) -> str:
    """The chosen setting and the figures :func:`calibrate` saw (its ``figures``), one line for
    people (``tactile-export`` prints it, ``tactile-check`` shows it)."""
    raw, sm = f["raw"], f["smoothed"]

    def num(v, fmt):
        return "-" if v is None else format(v, fmt)

    n = f["streams"]
    by = f" {HELD_OUT}" if f.get(LABELLED_BY) == FIRST_TRAINING else ""
    return (f"{f['setting']} (calibrated on {n} validation stream{'s' if n != 1 else ''}{by}, "
            f"{raw['minutes']:.1f} min: correct stable labels {sm['accuracy'] * 100:.1f} % "
            f"(raw {raw['accuracy'] * 100:.1f} %), uncertain {sm['uncertain'] * 100:.1f} %, "
            f"false changes/min {num(sm['false_per_min'], '.2f')} (raw "
            f"{num(raw['false_per_min'], '.2f')}), change latency median "
            f"{num(sm['latency_median_s'], '.2f')} s"
            f"{'' if f['met_limit'] else '; the change limit NOT met'})")


__all__ = ["FIRST_TRAINING", "HELD_OUT", "LABELLED_BY", "MAX_FALSE_PER_MIN", "MAX_UNCERTAIN",
           "Calibration", "calibrate", "default_grid", "refusal", "summary_line"]
