"""Labels from a pen in one call: :func:`labels` (also ``tactile.runtime.labels``)."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator

import tactile.device  # noqa: F401  (registers sim://)
from tactile.device.decoder import StreamDecoder
from tactile.device.ports import open_port, read_some, wait_for_port
from tactile.errors import DeviceError
from tactile.runtime.cli import Runner, Summary
from tactile.runtime.model import Model
from tactile.runtime.stream import Label, Smoother, Stream


class _Collect:
    """The printer interface of :class:`~tactile.runtime.cli.Runner`, collecting labels."""

    def __init__(self, on_event: Callable[[str, dict], None] | None) -> None:
        self.labels: list[Label] = []
        self.on_event = on_event

    def label(self, lab: Label) -> None:
        self.labels.append(lab)

    def event(self, kind: str, **fields) -> None:
        if self.on_event is not None:
            self.on_event(kind, fields)


def labels(
    port: str,
    model: Model | str | os.PathLike,
    *,
    hop: int | None = None,
    smoother: Smoother | None = None,
    baud: int = 115200,
    seconds: float = math.inf,
    reconnect: bool = True,
    on_event: Callable[[str, dict], None] | None = None,
) -> Iterator[Label]:
    """Yield one :class:`~tactile.runtime.stream.Label` per window read from the pen at ``port``
    (a device path or a pyserial URL), classified by ``model`` (a
    :class:`~tactile.runtime.model.Model` or the path of an exported ``.onnx``).

    It does what ``tactile-run`` does between the port and the labels: decodes the stream,
    checks the device's header against the model's contract (channels, units, rate:
    :class:`~tactile.errors.ModelContractError` otherwise), converts counts to units
    (:func:`~tactile.runtime.units.to_units`), starts a new window after lost samples, and, with
    ``reconnect``, reopens a vanished port (as after an unplug) until it is back. ``on_event``
    gets ``("gap", {"seq", "missing", "reason"})`` and ``("reconnect", {"port"})``. It stops
    after ``seconds`` (wall time) or when the caller stops iterating (the port is then closed).

    Example::

        from tactile.runtime import labels

        for lab in labels("/dev/ttyACM0", "model.onnx"):
            print(lab.seq, lab.label, round(lab.probability, 2))   # or lab.probabilities

    Raises :class:`~tactile.errors.DeviceError` if the port cannot be opened (or, without
    ``reconnect``, is lost).
    """
    if not isinstance(model, Model):
        model = Model(model)
    out = _Collect(on_event)
    runner = Runner(model, Stream.for_model(model, hop, smoother), out, Summary())
    decoder = StreamDecoder(csv_rate_hz=model.contract.sample_rate_hz)
    deadline = time.monotonic() + seconds
    link = open_port(port, baud)
    try:
        while time.monotonic() < deadline:
            data, e = read_some(link)  # one read of the port: nothing read is dropped
            if e is not None:
                link.close()
                link = None
                if not reconnect:
                    raise DeviceError(f"{port}: lost ({e})") from None
                link = wait_for_port(port, baud, {"flag": False}, lambda _msg: None, deadline)
                if link is None:
                    return
                decoder.reconnected()
                runner.stream.reset()
                out.event("reconnect", port=port)
                continue
            if data:
                runner.handle(decoder.feed(data))
                yield from out.labels
                out.labels.clear()
    finally:
        if link is not None:
            link.close()
