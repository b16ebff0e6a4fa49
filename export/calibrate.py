"""The label stream's defaults of an exported file, calibrated on the run's validation takes.

``tactile-export RUN -o F --data DATA`` plays the run's validation takes of DATA (never its
test takes) through the file as the board will run it (the runtime's own
:class:`~tactile.runtime.model.Model` and :class:`~tactile.runtime.stream.Stream`), cut into
pieces of 30 s and ordered so that neighbours differ in class
(:mod:`tactile.postprocess.streams`), lets :func:`~tactile.postprocess.calibration.calibrate`
choose a setting, and writes it with the figures it saw into the file's ``postprocess.*`` keys
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
from tactile.postprocess.calibration import calibrate, summary_line
from tactile.postprocess.smoothing import settings_to_metadata
from tactile.postprocess.streams import DWELL_S, Piece, make_streams, run_pieces, shortfall
from tactile.runtime.model import Model
from tactile.runtime.stream import Stream
from tactile.training.label_stream import group_of, validation_rows


def take_pieces(model: Model, take, rows: tuple[int, int], dwell_s: float = DWELL_S
                ) -> list[Piece]:
    """Pieces of rows [first, end) of ``take`` as the runtime labels them: each gap-free
    segment through a fresh :class:`Stream` (window times from the segment's first sample,
    s), cut into pieces of ``dwell_s`` s. The take's label must be one of the model's."""
    c = model.contract
    cols = [list(take.channels).index(ch) for ch in c.channels]
    values = take.values()[:, cols].astype(np.float32)
    label = c.classes.index(take.label)
    out = []
    for a, b in take.segments():
        a, b = max(a, rows[0]), min(b, rows[1])
        if b - a < c.window:
            continue
        stream = Stream.for_model(model)
        stream.accept(values[a:b], seq=0, t_us=0, period_us=1e6 / c.sample_rate_hz)
        t, probs = [], []
        while stream.ready():
            lab = stream.classify()
            t.append(lab.t_us / 1e6)
            probs.append([lab.probabilities[k] for k in c.classes])
        out += run_pieces(label, np.array(t), np.array(probs), dwell_s)
    return out


def calibrate_file(final: onnx.ModelProto, ck: dict, cfg, data: Path | None, log=print,
                   warn=None) -> dict | None:
    """Add the ``postprocess.*`` keys to ``final`` (its contract already attached) when the
    run's validation takes in ``data`` make enough stream; returns what the calibration saw
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
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "model.onnx"
        onnx.save(final, path)
        model = Model(path)
        groups: dict[str, list[Piece]] = {}
        for i, r in rows.items():
            if takes[i].label in model.contract.classes:
                groups.setdefault(group_of(takes[i]), []).extend(take_pieces(model, takes[i], r))
    c = model.contract
    streams = make_streams(groups, c.classes, c.hop / c.sample_rate_hz)
    why = shortfall(streams) if streams else "no validation window"
    if why:
        warn(f"tactile-export: no label stream defaults in the file (it runs raw): too little "
             f"validation data ({why})")
        return None
    cal = calibrate(streams)
    onnx.helper.set_model_props(final, {**{p.key: p.value for p in final.metadata_props},
                                        **settings_to_metadata(cal.settings, cal.figures)})
    log(f"label stream defaults: {summary_line(cal.figures)}")
    return cal.figures


__all__ = ["calibrate_file", "take_pieces"]
