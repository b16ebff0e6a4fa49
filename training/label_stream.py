"""A run's label stream in PyTorch: raw against post-processed, on streams made of its takes.

``tactile-eval`` measures what a user of the exported model would see: the samples of the run's
test takes cut into pieces of 30 s and joined one after the other into one stream per user,
neighbours of different classes (:mod:`tactile.postprocess.streams`), then windowed and run
through the checkpoint as the runtime runs a pen (windows across piece boundaries, a carried
state carried on; :func:`stream_windows`), the raw argmax against the post-processed stable label
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
from tactile.postprocess.calibration import (
    FIRST_TRAINING,
    HELD_OUT,
    LABELLED_BY,
    MAX_UNCERTAIN,
    Calibration,
    calibrate,
    refusal,
)
from tactile.postprocess.metrics import WindowStream, compare
from tactile.postprocess.smoothing import SmoothingSettings
from tactile.postprocess.streams import (
    DWELL_S,
    Piece,
    SampleStream,
    make_streams,
    run_pieces,
    shortfall,
    window_ends,
    window_stream,
)
from tactile.training.data import Windows, channel_index, find_test_split, split_takes

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


def stored_streams(ck: dict) -> list[WindowStream] | None:
    """The validation takes' label streams as the first training's model labelled them, kept
    in the checkpoint of a run whose final model refit on those takes
    (:func:`tactile.training.run_files.held_out_streams`); None for a run without them (no
    refit, or saved before they were kept)."""
    kept = ck.get("held_out_streams")
    if not kept:
        return None
    classes = tuple(ck["classes"])
    return [WindowStream(s["t"].numpy(), s["truth"].numpy(), s["probs"].numpy(), classes)
            for s in kept]


IN_SAMPLE = ("the final model's own labels of takes it refit on (a run saved before runs kept "
             "their first training's labels): figures in-sample, train it again for held-out "
             "ones")


def in_sample(ck: dict) -> bool:
    """Whether a run's final model refit on its validation takes and the checkpoint keeps no
    held-out labels of them (saved before runs kept them): its own labels are in-sample."""
    m = ck.get("metrics") or {}
    return not ck.get("held_out_streams") and bool(m.get("refit_epochs")) and \
        m.get("refit_kept") is not False


def calibration(streams: list[WindowStream], held: bool) -> tuple[Calibration, str | None]:
    """The setting :func:`~tactile.postprocess.calibration.calibrate` picks on validation
    ``streams`` within a file's limits (``held``: the first training's labels, said in its
    figures), and why a file would not carry it
    (:func:`~tactile.postprocess.calibration.refusal`; None: it would): tactile-export's rule,
    which tactile-eval follows."""
    cal = calibrate(streams, max_uncertain=MAX_UNCERTAIN)
    if held:
        cal.figures[LABELLED_BY] = FIRST_TRAINING
    return cal, refusal(cal)


def group_of(take) -> str:
    """A take's stream: its ``user`` (``-`` for takes that name none)."""
    return str(take.meta.get("user", "-"))


def take_pieces(take, rows: tuple[int, int], classes: tuple[str, ...],
                channels: tuple[str, ...], rate_hz: float, dwell_s: float = DWELL_S
                ) -> list[Piece]:
    """Sample pieces of rows [first, end) of ``take`` (its label one of ``classes``): each
    gap-free segment's samples in ``channels``' order (all of the take's when empty), cut into
    pieces of at most ``dwell_s`` s at ``rate_hz``."""
    values = take.values()[:, channel_index(take, channels)].astype(np.float32)
    label = classes.index(take.label)
    out = []
    for a, b in take.segments():
        a, b = max(a, rows[0]), min(b, rows[1])
        if b > a:
            out += run_pieces(label, values[a:b], rate_hz, dwell_s)
    return out


def pieces(takes: list, rows: dict[int, tuple[int, int]] | None, classes: tuple[str, ...],
           channels: tuple[str, ...], rate_hz: float, dwell_s: float = DWELL_S
           ) -> dict[str, list[Piece]]:
    """``{group: pieces}`` of rows ``rows`` (``{take index: (first, end)}``; None: every row of
    every take) of the takes of ``classes`` (:func:`take_pieces`, :func:`group_of`)."""
    if rows is None:
        rows = {i: (0, len(t.seq)) for i, t in enumerate(takes)}
    groups: dict[str, list[Piece]] = {}
    for i, r in rows.items():
        if takes[i].label in classes:
            groups.setdefault(group_of(takes[i]), []).extend(
                take_pieces(takes[i], r, classes, channels, rate_hz, dwell_s))
    return groups


def stream_windows(stream: SampleStream, window: int, hop: int) -> Windows:
    """The windows a pen makes on the joined ``stream``
    (:func:`~tactile.postprocess.streams.window_ends`, every ``hop`` samples) as one gap-free
    run (take 0, run 0), so that :func:`tactile.training.evaluate.predict` runs them as the
    runtime does: a zero state per window, or one state carried across the whole stream, piece
    boundaries included. ``y``: each window's last sample's class."""
    ends = window_ends(len(stream.truth), window, hop)
    starts = ends - (window - 1)
    x = stream.values[starts[:, None] + np.arange(window)[None, :]]
    zeros = np.zeros(len(ends), np.int64)
    return Windows(x, stream.truth[ends], zeros, starts, zeros.copy())


def run_streams(groups: dict[str, list[Piece]], classes: tuple[str, ...], rate_hz: float,
                window: int, hop: int, predict, seed: int = 0) -> list[WindowStream]:
    """Each group's pieces joined (:func:`~tactile.postprocess.streams.make_streams`) and run
    through ``predict(windows)`` (probabilities (N, classes)); streams shorter than one window
    are left out."""
    out = []
    for s in make_streams(groups, classes, rate_hz, seed):
        if len(s.truth) >= window:
            out.append(window_stream(s, predict(stream_windows(s, window, hop)), window, hop))
    return out


def stream_figures(model, ck: dict, takes: list, folder: str,
                   test_rows: dict[int, tuple[int, int]] | None, predict,
                   settings: SmoothingSettings | None = None, seed: int = 0) -> dict:
    """The label stream figures of the test rows ``test_rows`` of ``takes`` (None: all of
    them): ``{"setting", "source", "calibration" (what it saw on validation, or None),
    "streams", "dwell_s", "raw", "smoothed"}`` (``raw`` and ``smoothed`` as
    :func:`~tactile.postprocess.metrics.figures`). ``predict(windows)``: the model's
    probabilities (N, classes) of windows (:func:`tactile.training.evaluate.predict`).
    ``settings`` None: calibrated on the run's validation takes of ``takes``
    (:func:`validation_rows`), else :data:`FALLBACK`, saying why."""
    cfg = model.cfg
    classes, channels = tuple(ck["classes"]), tuple(ck["channels"])
    rate = float(ck["sample_rate_hz"])

    def streams_of(rows):
        return run_streams(pieces(takes, rows, classes, channels, rate), classes, rate,
                           cfg.window, cfg.hop, predict, seed)

    seen, source = None, "given"
    if settings is None:
        rows, why = validation_rows(takes, ck, cfg, folder)
        streams, held = [], stored_streams(ck)
        if rows is not None:
            streams = held if held is not None else streams_of(rows)
            why = (shortfall(streams) if streams else "no validation window") or ""
        if why:
            settings, source = FALLBACK, f"not calibrated: {why}"
        else:
            cal, refused = calibration(streams, held is not None)
            settings, seen = cal.settings, cal.figures
            n = len(streams)
            source = (f"calibrated on the run's validation takes: {n} stream"
                      f"{'s' if n != 1 else ''}, {sum(s.minutes for s in streams):.1f} min"
                      + (f", {HELD_OUT}" if held is not None else
                         f", {IN_SAMPLE}" if in_sample(ck) else ""))
            if refused:  # tactile-export's rule: then the file carries no defaults
                settings = SmoothingSettings()
                source += f"; {refused}: raw, as tactile-export leaves the file"
    test_streams = streams_of(test_rows)
    if not test_streams:
        raise ConfigError("label stream: no test stream as long as one window")
    return {"setting": settings.describe(), "source": source, "calibration": seen,
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

    n = f["streams"]
    lines = [f"label stream: {n} stream{'s' if n != 1 else ''} of the evaluated takes in pieces of "
             f"{f['dwell_s']:g} s, {f['raw']['minutes']:.1f} min; post-processed with "
             f"{f['setting']} ({f['source']})",
             f"  {'':36s}{'raw':>10s}{'post-processed':>16s}"]
    for name, key, pct in ROWS:
        lines.append(f"  {name:36s}{fmt(f['raw'][key], pct):>10s}"
                     f"{fmt(f['smoothed'][key], pct):>16s}")
    return "\n".join(lines)


__all__ = ["FALLBACK", "IN_SAMPLE", "calibration", "group_of", "in_sample", "pieces", "run_streams",
           "stored_streams", "stream_figures", "stream_table", "stream_windows", "take_pieces",
           "validation_rows"]
