"""Labels from a pen in one call: :func:`labels` (also ``tactile.runtime.labels``)."""

from __future__ import annotations

import math
import numbers
import os
import time
from collections.abc import Callable, Iterator, Mapping

import tactile.device  # noqa: F401  (registers sim://)
from tactile.device.link import Connection, LinkSettings
from tactile.device.protocol import StreamDecoder
from tactile.errors import ConfigError
from tactile.postprocess.smoothing import SmoothingSettings
from tactile.runtime.model import Model
from tactile.runtime.runner import Runner, Summary, post_processor
from tactile.runtime.stream import Label, Stream


class _Collect:
    """The printer interface of :class:`~tactile.runtime.runner.Runner`, collecting labels."""

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
    smoothing: SmoothingSettings | Mapping | str | None = None,
    baud: int = 115200,
    seconds: float = math.inf,
    reconnect: bool = True,
    stall_timeout: float = 2.0,
    on_event: Callable[[str, dict], None] | None = None,
    say: Callable[[str], None] | None = None,
) -> Iterator[Label]:
    """Yield one :class:`~tactile.runtime.stream.Label` per window read from the pen at ``port``
    (a device path or a pyserial URL), classified by ``model`` (a
    :class:`~tactile.runtime.model.Model` or the path of an exported ``.onnx``).

    It does what ``tactile-run`` does between the port and the labels, through the same
    :class:`~tactile.device.link.connection.Connection`: decodes the stream, checks the device's
    header against the model's contract (channels, units, rate:
    :class:`~tactile.errors.ModelContractError` otherwise), converts counts to units
    (:func:`~tactile.runtime.units.to_units`), starts a new window after lost samples, and, with
    ``reconnect``, reopens a vanished port (as after an unplug) once the same pen is back (its
    header, its USB serial number when it has one; another device that takes its name is
    refused). ``on_event`` gets ``("gap", {"seq", "missing", "reason"})``,
    ``("stall", {"seconds"})`` (no data for ``stall_timeout`` s, once per silence) and
    ``("reconnect", {"port", "offline_s"})``, ``("change", {"from", "to", "t", "seq"})`` (the stable
    label changed; ``from`` None after a reset) and ``("invalid", {"seq", "t"})`` (a window
    whose values the model cannot take: no label for it); ``say``, if given, the diagnostic lines
    ``tactile-run`` writes on stderr (lost, waiting, refused). It stops after ``seconds`` (wall
    time) or when the caller stops iterating (the port is then closed).

    Each label is post-processed as ``tactile-run`` does it
    (:func:`~tactile.runtime.runner.post_processor`): ``smoothing`` None takes the model's
    defaults (a file without ``postprocess.*`` metadata: raw labels, ``lab.smoothed`` None);
    ``"raw"`` none; a :class:`~tactile.postprocess.smoothing.SmoothingSettings` that setting; a dict
    of ``smooth`` (``"5"`` windows, ``"1.5s"``), ``p_min``, ``hold`` those in place of the
    model's, as the options ``--smooth``, ``--p-min``, ``--hold``. ``lab.smoothed.label`` is then
    the stable label or ``"uncertain"``, with ``.p``, ``.stable`` and ``.reset`` (the reason of
    a reset just before this window: ``"gap"``, ``"restart"``, ``"reconnect"``).

    Example::

        from tactile.runtime import labels

        for lab in labels("/dev/ttyACM0", "model.onnx"):
            print(lab.seq, lab.label, round(lab.probability, 2))   # or lab.probabilities

        for lab in labels("/dev/ttyACM0", "model.onnx", smoothing={"smooth": "5", "p_min": 0.6,
                                                                     "hold": 2}):
            print(lab.seq, lab.smoothed.label)                     # stable, or "uncertain"

    Raises :class:`~tactile.errors.DeviceError` if the port cannot be opened (or, without
    ``reconnect``, is lost: after the labels of the bytes that came before the loss), and
    :class:`~tactile.errors.ConfigError` for a bad argument (``hop`` not a whole number,
    ``seconds`` not a number > 0, ...) at the first label asked for.
    """
    if isinstance(seconds, bool) or not isinstance(seconds, numbers.Real) or not seconds > 0:
        raise ConfigError(f"seconds {seconds!r}: must be a number > 0 (math.inf, the default: "
                          "until the caller stops)")  # (NaN, -1: no label, and no word)
    if not isinstance(model, Model):
        model = Model(model)
    out = _Collect(on_event)
    post = post_processor(model, smoothing)
    runner = Runner(model, Stream.for_model(model, hop, post), out, Summary())
    decoder = StreamDecoder(csv_rate_hz=model.contract.sample_rate_hz)
    deadline = time.monotonic() + seconds
    settings = LinkSettings(port, baud, reconnect=reconnect, stall_timeout=stall_timeout)
    with Connection(settings, decoder, say=say, deadline=deadline) as conn:
        conn.open()
        for chunk in conn.chunks():  # until the deadline, or the pen did not come back in time
            runner.handle(chunk.events)
            yield from out.labels
            out.labels.clear()
