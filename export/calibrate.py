"""The label stream's defaults of an exported file, calibrated on the run's validation takes.

``tactile-export RUN -o F --data DATA`` plays the run's validation takes of DATA (never its
test takes) through the file as the board will run it (for a run that refit on them, the
default, the run's first training labelled them instead, and the checkpoint keeps those labels:
the final model's own would calibrate on takes it has trained on): their samples cut into
pieces of 30 s, each user's pieces ordered so that neighbours differ in class and joined
into one stream (:mod:`tactile.postprocess.streams`), which the runtime's own
:class:`~tactile.runtime.model.Model` and :class:`~tactile.runtime.stream.Stream` label as a
pen's (windows across the pieces' boundaries, a carried state carried on), lets
:func:`~tactile.postprocess.calibration.calibrate` choose a setting, and writes it with the
figures it saw into the file's ``postprocess.*`` keys
(:func:`~tactile.postprocess.smoothing.settings_to_metadata`). Without DATA, or with too little
validation data, the file gets no defaults (it runs raw), and one stderr line says why.

``tactile-eval`` chooses the same way on the same takes with the checkpoint's probabilities
(:mod:`tactile.training.label_stream`); the two agree wherever the file's probabilities agree
with PyTorch's (the parity check).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import onnx

from tactile.device.recordings import load_dataset
from tactile.postprocess.calibration import summary_line
from tactile.postprocess.metrics import WindowStream
from tactile.postprocess.smoothing import settings_to_metadata
from tactile.postprocess.streams import Piece, SampleStream, make_streams, shortfall, window_stream
from tactile.runtime.model import Model
from tactile.runtime.stream import Stream
from tactile.training.label_stream import (
    IN_SAMPLE,
    calibration,
    in_sample,
    pieces,
    stored_streams,
    validation_rows,
)


def run_stream(model: Model, stream: SampleStream) -> WindowStream | None:
    """The joined ``stream`` through the runtime as a pen feeds it: one fresh
    :class:`Stream`, the samples in order with consecutive seq numbers and no gap, one hop at a
    time (so windows straddle the pieces' boundaries and a carried state carries on), every
    window classified; None when the stream is shorter than one window."""
    c = model.contract
    if len(stream.truth) < c.window:
        return None
    runner = Stream.for_model(model)
    probs = []
    for a in range(0, len(stream.values), c.hop):
        runner.accept(stream.values[a:a + c.hop], seq=a, t_us=round(a * 1e6 / stream.rate_hz))
        while runner.ready():
            lab = runner.classify()
            probs.append([lab.probabilities[k] for k in c.classes])
    return window_stream(stream, np.array(probs), c.window, c.hop)


def run_streams(model: Model, groups: dict[str, list[Piece]], seed: int = 0
                ) -> list[WindowStream]:
    """Each group's pieces joined (:func:`~tactile.postprocess.streams.make_streams`) and run
    through the file (:func:`run_stream`); streams shorter than one window are left out."""
    c = model.contract
    runs = (run_stream(model, s) for s in make_streams(groups, c.classes, c.sample_rate_hz, seed))
    return [r for r in runs if r is not None]


def calibrate_file(final: onnx.ModelProto, ck: dict, cfg, data: Path | None, log=print,
                   warn=None) -> dict | None:
    """Add the ``postprocess.*`` keys to ``final`` (its contract already attached) when the
    run's validation takes in ``data`` make enough stream and the chosen setting labels at
    least as many of their windows right as the raw stream; returns what the calibration saw
    (None: no defaults written, ``warn`` (default: a line on stderr) said why, unless there is
    no ``data``). ``cfg``: the checkpoint's training config (to draw its split again)."""
    warn = warn or (lambda line: print(line, file=sys.stderr))
    if data is None:
        return None
    takes = load_dataset(data)
    rows, why = validation_rows(takes, ck, cfg, Path(data).name)
    if rows is None:
        warn(f"tactile-export: no label stream defaults in the file (it runs raw): {why}")
        return None
    streams = held = stored_streams(ck)
    if held is None:  # a run without a refit: the file's own labels are held out
        if in_sample(ck):
            warn(f"tactile-export: warning: label stream calibrated on {IN_SAMPLE}")
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "model.onnx"
            onnx.save(final, path)
            model = Model(path)
            c = model.contract
            streams = run_streams(model, pieces(takes, rows, c.classes, c.channels,
                                                c.sample_rate_hz))
    why = shortfall(streams) if streams else "no validation window"
    if why:
        warn(f"tactile-export: no label stream defaults in the file (it runs raw): too little "
             f"validation data ({why})")
        return None
    cal, why = calibration(streams, held is not None)
    if why:
        warn(f"tactile-export: no label stream defaults in the file (it runs raw): on the "
             f"validation streams {why}")
        return None
    onnx.helper.set_model_props(final, {**{p.key: p.value for p in final.metadata_props},
                                        **settings_to_metadata(cal.settings, cal.figures)})
    log(f"label stream defaults: {summary_line(cal.figures)}")
    return cal.figures


__all__ = ["calibrate_file", "run_stream", "run_streams"]
