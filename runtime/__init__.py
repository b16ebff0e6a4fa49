"""tactile.runtime: labels from a pen with onnxruntime, numpy and pyserial only (never torch).

``labels(port, model)`` (:func:`tactile.runtime.pen.labels`) yields one label per window;
``to_units(info, raw)`` (:func:`tactile.runtime.units.to_units`) converts counts to units.
Both are imported on first use, so that ``import tactile.runtime.stream`` stays light.
"""


def __getattr__(name: str):
    if name == "labels":
        from tactile.runtime.pen import labels

        return labels
    if name == "to_units":
        from tactile.runtime.units import to_units

        return to_units
    raise AttributeError(f"module 'tactile.runtime' has no attribute {name!r}")


__all__ = ["labels", "to_units"]
