"""tactile.runtime: labels from a pen with onnxruntime, numpy and pyserial only (never torch).

``labels(port, model)`` (:func:`tactile.runtime.pen.labels`) yields one label per window;
``to_units(info, raw)`` (:func:`tactile.runtime.units.to_units`) converts counts to units.
:class:`~tactile.runtime.model.Model` (the exported model, stateless) and
:class:`~tactile.runtime.stream.Stream` (one pen's windows and state) are the pieces
``tactile-run`` is made of, with :class:`~tactile.postprocess.smoothing.PostProcessor` (a
stream's averaged, stable label and its changes;
:class:`~tactile.postprocess.smoothing.SmoothingSettings`);
:class:`~tactile.runtime.runner.Runner` drives them from a pen's decoded events
(:func:`~tactile.runtime.runner.read_pen`, the serial loop; :func:`~tactile.runtime.runner.replay`,
a recorded take); :class:`~tactile.runtime.live.Live`
is the live web page. Each name is imported on first use, so that
``import tactile.runtime.stream`` stays light. The command lines are in
:mod:`tactile.runtime.commands`.
"""

import importlib

_HOME = {
    "labels": "pen",
    "to_units": "units",
    "Model": "model",
    "Label": "stream",
    "Stream": "stream",
    "PostProcessor": "tactile.postprocess.smoothing",
    "SmoothingSettings": "tactile.postprocess.smoothing",
    "UNCERTAIN": "tactile.postprocess.smoothing",
    "Printer": "runner",
    "Runner": "runner",
    "Summary": "runner",
    "check_device": "runner",
    "read_pen": "runner",
    "replay": "runner",
    "Live": "live",
}


def __getattr__(name: str):
    if name in _HOME:
        home = _HOME[name]  # a module of the runtime, or a full name (the shared core's)
        return getattr(importlib.import_module(home if "." in home else
                                               f"tactile.runtime.{home}"), name)
    raise AttributeError(f"module 'tactile.runtime' has no attribute {name!r}")


__all__ = list(_HOME)
