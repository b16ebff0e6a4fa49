"""The runner: decoder events -> stream -> labels, and the loops that feed it (``tactile-run``).

:class:`Runner` takes a pen's decoded events in order (headers, samples, gaps, and the link's
stalls and reconnections), checks the device against the model's contract
(:func:`check_device`), classifies each window (post-processed by the stream's
:class:`~tactile.postprocess.smoothing.PostProcessor`, :func:`post_processor`) and hands labels and
events to a :class:`Printer` (stdout) and a :class:`Summary` (counters). Two loops feed it:
:func:`read_pen`, the serial loop over a :class:`~tactile.device.link.connection.Connection` (it
reconnects to the same pen only), and :func:`replay`, a recorded take as fast as it can.
Diagnostics (:func:`say`) go to stderr, prefixed ``tactile-run:``.
"""

from __future__ import annotations

import csv
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import tactile.device  # noqa: F401  (registers sim://)
from tactile.device.link import Connection, LinkSettings, Reconnected, Stall, find_port, keep_trying
from tactile.device.protocol import DeviceInfo, Gap, Header, Samples, StreamDecoder
from tactile.errors import ConfigError, ModelContractError, OutputError, RecordingError
from tactile.postprocess.smoothing import PostProcessor, SmoothingSettings, override
from tactile.runtime.model import Model
from tactile.runtime.stream import InvalidWindow, Label, Stream
from tactile.runtime.units import to_units


@dataclass
class Summary:
    """A run's counters, for the summary line on stderr (:meth:`to_dict`) and the live page."""

    windows: int = 0
    labels: Counter = field(default_factory=Counter)
    gaps: int = 0
    reconnects: int = 0
    stalls: int = 0
    before_header: int = 0  # samples that arrived before the first header (not classified)
    invalid: int = 0  # windows whose model output was not finite: no label
    started: float = field(default_factory=time.monotonic)
    first_label_s: float | None = None

    def to_dict(self, decoder_stats: dict | None) -> dict:
        return {
            "windows": self.windows,
            "labels": dict(self.labels),
            "gaps": self.gaps,
            "reconnects": self.reconnects,
            "stalls": self.stalls,
            "samples_before_header": self.before_header,
            "invalid_windows": self.invalid,
            "first_label_s": self.first_label_s,
            "seconds": round(time.monotonic() - self.started, 3),
            "decoder": decoder_stats,
        }


class Printer:
    """Writes labels and events in the chosen format, flushing each line.

    ``smoothed``: the labels carry a post-processor's result (``tactile-run`` without ``--raw``,
    with settings from the options or the model): CSV fills the columns ``smoothed``,
    ``smoothed_p``, ``stable`` and ``reset``, and a text line ends with the smoothed label.
    Without it the output is the raw stream's alone (those CSV columns stay, empty: one set of
    columns either way).
    """

    def __init__(self, fmt: str, classes: tuple[str, ...], out=None,
                 smoothed: bool = False) -> None:
        # sys.stdout as it is now, not as it was at import (contextlib.redirect_stdout works)
        out = sys.stdout if out is None else out
        self.fmt, self.classes, self.out, self.smoothed = fmt, classes, out, smoothed
        if fmt == "csv":  # an event is a row of its own: its seq (if any) and `event` filled
            self._csv = csv.writer(out, lineterminator="\n")  # quotes what needs quoting
            self._row(["t", "seq", "label", "p", "latency_ms", "smoothed", "smoothed_p", "stable",
                       "reset", *classes, "event"])

    def _row(self, cells: list) -> None:
        with self._writing():
            self._csv.writerow(cells)
            self.out.flush()

    def _print(self, line: str) -> None:
        with self._writing():
            print(line, file=self.out, flush=True)

    @contextmanager
    def _writing(self) -> Iterator[None]:
        """stdout that cannot take a line (a full disk, an I/O error) is :class:`OutputError`
        (exit 4: a service may restart); a reader that went away stays BrokenPipeError (the
        command stops quietly)."""
        try:
            yield
        except BrokenPipeError:
            raise
        except OSError as e:
            raise OutputError(f"stdout: cannot write the labels ({e.strerror or e})") from None

    def label(self, lab: Label) -> None:
        sm = lab.smoothed if self.smoothed else None
        if self.fmt == "csv":
            extra = ["", "", ""] if sm is None else \
                [f"{sm.p:.6f}", str(sm.stable).lower(), sm.reset or ""]
            self._row([f"{lab.t_us / 1e6:.6f}", lab.seq, lab.label, f"{lab.probability:.6f}",
                       f"{lab.latency_ms:.3f}", sm.label if sm is not None else "", *extra,
                       *(f"{lab.probabilities[c]:.6f}" for c in self.classes), ""])
            return
        if self.fmt == "jsonl":
            line = json.dumps(lab.to_dict())
        else:
            line = f"{lab.t_us / 1e6:10.2f} s  #{lab.seq:<8d} {lab.label}  " \
                   f"p={lab.probability:.3f}"
            if sm is not None:  # the stable label, or `uncertain` and the leading class
                line += f"  -> {sm.label} p={sm.p:.3f}" if sm.stable else \
                    f"  -> {sm.label} ({sm.leader} p={sm.p:.3f})"
                if sm.reset is not None:
                    line += f"  [reset: {sm.reset}]"
        self._print(line)

    def event(self, kind: str, **fields) -> None:
        """Gaps, stalls, reconnects and changes of the stable label: a JSON object in jsonl
        mode, a row with the `event` column filled in csv mode, a ``#`` comment line in text
        mode."""
        if self.fmt == "jsonl":
            self._print(json.dumps({"event": kind, **fields}))
            return
        shown = {k: "" if v is None else v for k, v in fields.items()}  # JSON's null: empty
        if self.fmt == "csv":
            what = " ".join([kind, *(f"{k}={v}" for k, v in shown.items() if k != "seq")])
            blank = len(self.classes) + 7  # label .. reset, the classes
            self._row(["", fields.get("seq", ""), *[""] * blank, what])
        else:
            self._print(f"# {kind} " + " ".join(f"{k}={v}" for k, v in shown.items()))


def post_processor(model: Model, smoothing=None) -> PostProcessor | None:
    """The label stream's post-processor for ``model``, or None (raw labels only).

    ``smoothing``: None, the model's defaults (its ``postprocess.*`` metadata; a file without
    them: None); ``"raw"``, none; a :class:`~tactile.postprocess.smoothing.SmoothingSettings`, that;
    a mapping with any of ``smooth`` (``N`` windows or ``Ts``,
    :func:`~tactile.postprocess.smoothing.parse_smooth_option`),
    ``p_min`` and ``hold``, those values in place of the model's (as ``tactile-run``'s
    options). A bad value is a one-line :class:`ConfigError`; a model with a class named
    ``uncertain`` (reserved) is a :class:`ModelContractError` once post-processing is on.
    """
    if isinstance(smoothing, str) and smoothing == "raw":
        return None
    if smoothing is None or isinstance(smoothing, SmoothingSettings):
        settings = model.postprocess if smoothing is None else smoothing
    elif isinstance(smoothing, Mapping):
        unknown = sorted(set(smoothing) - {"smooth", "p_min", "hold"})
        if unknown:
            raise ConfigError(f"smoothing key {unknown[0]!r}: expected smooth, p_min, hold")
        settings = override(model.postprocess, **smoothing)
    else:
        raise ConfigError(f"smoothing {smoothing!r}: None (the model's), 'raw', a "
                          "SmoothingSettings or a dict of smooth, p_min, hold")
    if settings is None:
        return None
    try:
        return PostProcessor(settings, model.contract.classes)
    except ConfigError as e:  # the reserved class name: the file cannot be post-processed
        raise ModelContractError(f"{model.path}: {e}") from None


def check_device(model: Model, info: DeviceInfo) -> np.ndarray:
    """Where the model's channels are among the device's: the columns (model order) of the
    device's samples that the model reads. Each of the model's channels must be there, by name,
    in the model's unit, at the model's rate (a CSV-line device, which declares neither units
    nor rate, is taken in the model's); a device that sends more channels than the model uses
    is fine, and the ones left unused are named once on stderr."""
    want = model.contract.channels
    got = info.channel_names
    where = {name: i for i, name in enumerate(got)}
    missing = [name for name in want if name not in where]
    if missing:
        unnamed = info.device == "csv" and got == tuple(f"ch{i}" for i in range(len(got)))
        raise ModelContractError(
            f"the device sends no {_names(missing)}: the model reads {len(want)} channel"
            f"{'s' * (len(want) != 1)} ({_names(list(want))}), the device sends {len(got)} "
            f"({_names(list(got))})" + ("; a CSV device names its channels in a names line, which "
                                    "this port did not get (opened after it, and none came in "
                                    "the next 2 s of rows): restart the board with the port "
                                    "open, or have it repeat its names line" if unnamed
                                    else "")
        )
    columns = np.array([where[name] for name in want], np.intp)
    got_units = tuple(info.channels[i].unit for i in columns)
    if info.units_unknown:  # a CSV device: no units, no rate
        say(f"CSV device: its values are taken in the model's units "
            f"{list(model.contract.units)}, at the model's {model.contract.sample_rate_hz:g} Hz")
    elif got_units != model.contract.units:
        odd = [(name, g, w) for name, g, w in zip(want, got_units, model.contract.units)
               if g != w]
        name, g, w = odd[0]
        more = (f"; {len(odd) - 1} more channel{'s differ' if len(odd) > 2 else ' differs'}"
                if len(odd) > 1 else "")
        raise ModelContractError(
            f"device units differ from the model's: {name} in {g!r}, the model's in {w!r}{more}")
    if not math.isclose(info.sample_rate_hz, model.contract.sample_rate_hz, rel_tol=1e-3):
        raise ModelContractError(
            f"device rate {info.sample_rate_hz:g} Hz does not match the model's "
            f"{model.contract.sample_rate_hz:g} Hz"
        )
    unused = [name for name in got if name not in set(want)]
    if unused:
        say(f"the model reads {len(want)} of the device's {len(got)} channels; unused: "
            f"{_names(unused)}")
    return columns


def _names(names: list[str], most: int = 8) -> str:
    """At most ``most`` names, then how many more (a BioTac sends 88 channels)."""
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(names[:most]) + more


class Runner:
    """Decoder events -> stream -> labels. No I/O of its own beyond the printer."""

    def __init__(self, model: Model, stream: Stream, printer: Printer, summary: Summary):
        self.model, self.stream, self.printer, self.summary = model, stream, printer, summary
        self.info: DeviceInfo | None = None
        self.columns: np.ndarray | None = None  # the device's columns the model reads
        self.tap: Callable[[object], None] | None = None  # sees each decoder event (--serve)

    def handle(self, events: list) -> None:
        """Decoder events, and the link's (:mod:`~tactile.device.link.connection`), in order.

        A reconnection, a restart (a changed header, a ``restart`` gap) and a gap reset the
        stream (its LSTM state and post-processor, with that reason); a window whose stable
        label changes is followed by a ``change`` event (``from``, ``to``, ``t``, ``seq``)."""
        for ev in events:
            if self.tap is not None:
                self.tap(ev)
            if isinstance(ev, Reconnected):  # the same pen, restarted: a new window
                self.summary.reconnects += 1
                self.stream.reset("reconnect")
                self.printer.event("reconnect", port=ev.port, offline_s=ev.offline_s)
            elif isinstance(ev, Stall):
                self.summary.stalls += 1
                self.printer.event("stall", seconds=ev.seconds)
            elif isinstance(ev, Header):
                if ev.info != self.info:  # a new header, or the pen's again after a restart
                    self.columns = check_device(self.model, ev.info)
                if ev.changed:
                    self.stream.reset("restart")
                self.info = ev.info
            elif isinstance(ev, Gap):
                self.summary.gaps += 1
                self.stream.gap("restart" if ev.reason == "restart" else "gap")
                self.printer.event("gap", seq=ev.seq, missing=ev.missing, reason=ev.reason)
            elif isinstance(ev, Samples):
                if self.info is None:  # no header yet: we cannot check or scale these samples
                    self.summary.before_header += len(ev.raw)
                    continue
                period = 1e6 / self.info.sample_rate_hz
                values = to_units(self.info, ev.raw)[:, self.columns]
                self.stream.accept(values, ev.seq, ev.t_us, period)
                while self.stream.ready():
                    try:
                        lab = self.stream.classify()
                    except InvalidWindow as e:  # no label; said once, counted, an event
                        self.summary.invalid += 1
                        if self.summary.invalid == 1:
                            say(f"{e}; such windows are counted in the summary "
                                "(invalid_windows) and marked by 'invalid' events")
                        self.printer.event("invalid", seq=e.seq, t=e.t_us / 1e6)
                        continue
                    self.summary.windows += 1
                    self.summary.labels[lab.label] += 1
                    if self.summary.first_label_s is None:
                        self.summary.first_label_s = round(
                            time.monotonic() - self.summary.started, 3)
                    self.printer.label(lab)
                    if lab.smoothed is not None and lab.smoothed.event is not None:
                        change = dict(lab.smoothed.event)
                        self.printer.event(change.pop("event"), **change)


PEN_POLL_S = 0.5  # how often --wait without --port looks for a pen


def wait_for_pen(stop: dict, deadline: float, status_every: float) -> str | None:
    """``--wait`` without ``--port``: look for the one likely pen (:func:`find_port`) every
    :data:`PEN_POLL_S` s until it is attached, the user stops, or ``deadline`` (monotonic, from
    ``--seconds``) passes (None for the last two; the deadline says so on stderr). More than one
    likely pen is an error at once: waiting would not tell them apart."""
    start = time.monotonic()
    port = find_port(wait=True)
    if port is not None:
        return port
    say("no likely pen attached; waiting for one")
    port = keep_trying(lambda: find_port(wait=True), stop, say, "a likely pen", deadline,
                       status_every, (PEN_POLL_S, PEN_POLL_S))
    if port is None and not stop["flag"]:
        say(f"no pen attached after {time.monotonic() - start:.1f} s (--seconds); stopping")
    return port


def read_pen(runner: Runner, decoder: StreamDecoder, settings: LinkSettings, stop: dict,
             deadline: float = math.inf) -> None:
    """The serial loop: read, decode, classify, through a
    :class:`~tactile.device.link.connection.Connection` (it reconnects to the same pen only), until
    ``stop["flag"]`` is set (by a signal handler), ``deadline`` (``time.monotonic()``, from
    ``--seconds``) passes or the pen does not come back in time. A status line goes to stderr
    every ``settings.status_every`` s."""
    with Connection(settings, decoder, stop, say, deadline) as conn:
        if not conn.open():
            return
        last_status = time.monotonic()
        for chunk in conn.chunks():
            runner.handle(chunk.events)
            now = time.monotonic()
            if now - last_status >= settings.status_every:
                last_status = now
                _status(runner, decoder, conn.silent_for(now))


def _status(runner: Runner, decoder: StreamDecoder, silent: float | None) -> None:
    """The status line on stderr."""
    summary, st = runner.summary, decoder.stats
    notes = f"  no data for {silent:.0f} s" if silent is not None else ""
    if runner.info is None and summary.before_header:
        notes += f"  no device header yet: {summary.before_header} samples left unclassified"
    say(f"windows {summary.windows}  gaps {st.gaps} (lost {st.samples_lost})  "
        f"crc {st.crc_errors}  malformed {st.malformed}  "
        f"rejected {st.csv_rejected}  discarded {st.bytes_discarded} B  "
        f"reconnects {summary.reconnects}{notes}")


def replay(path: Path, runner: Runner, stop: dict, deadline: float = math.inf,
           clock: Callable[[], float] = time.monotonic) -> None:
    """Run a recorded take through the same stream, as fast as possible, until its end, a stop
    or ``deadline`` (on ``clock``, from ``--seconds``: the rest of the take is left out, with a
    line that says where it stopped)."""
    from tactile.device.recordings import read_take
    from tactile.device.recordings.reader import say_mismatch
    from tactile.device.recordings.take_meta import signal_order_differs

    take = read_take(path)
    if len(take.seq) == 0:
        raise RecordingError(f"{path}: the take holds no samples")
    differs = signal_order_differs(take.meta.get("signals", {}), [
        (s.name, s.channels) for s in runner.model.contract.signals])
    if differs:  # the channels go by name: each frame's sub-samples would be reordered
        raise ModelContractError(f"{path}: {differs}")
    say_mismatch(take)
    if take.truncated:
        say(f"{path}: its last row was cut short (the recording stopped mid-write); "
            "it is left out")
    window, segments = runner.stream.window, take.segments()
    longest = max(b - a for a, b in segments)
    if longest < window:  # a take too short for one window would end with no word
        say(f"{path}: {len(take.seq)} samples, fewer than the model's window of {window}: no "
            "label" if longest == len(take.seq) else
            f"{path}: no {window} samples without a gap (the model's window; the longest run: "
            f"{longest}): no label")
    runner.handle([Header(take.info)])
    # the take's gap lines, as the live stream gave them (a restart stays a restart), also
    # those before its first row and after its last; a seq jump no line records is a drop of
    # the samples it skips
    recorded: dict[int, list[Gap]] = {}
    for g in take.meta.get("gaps", []):
        recorded.setdefault(g["row"], []).append(Gap(g["seq"], g["missing"], g["reason"]))
    runner.handle(recorded.get(0, []))
    for a, b in segments:
        if stop["flag"]:
            break
        if a > 0:
            runner.handle(recorded.get(a) or [
                Gap(int(take.seq[a]), int(take.seq[a] - take.seq[a - 1] - 1), "drop")])
        i = a
        while i < b:
            if stop["flag"]:
                return
            if clock() >= deadline:
                say(f"--seconds: stopped before seq {int(take.seq[i])} ({i} of the "
                    f"{len(take.seq)} samples of {path} done)")
                return
            j = min(i + 256, b)
            # a run of samples starts where the recorded device time leaves the rate's steps
            # (a new frame of the pen, a clock reset), as the live stream gave them
            off = take.t_us[i:j] - take.t_us[i] - np.round(
                np.arange(j - i) * (1e6 / take.info.sample_rate_hz)).astype(np.int64)
            moved = np.flatnonzero(off)
            if moved.size:
                j = i + int(moved[0])
            runner.handle([Samples(int(take.seq[i]), int(take.t_us[i]), take.raw[i:j])])
            i = j
    if not stop["flag"]:
        runner.handle(recorded.get(len(take.seq), []))


def say(msg: str) -> None:
    """A diagnostic line on stderr, as ``tactile-run`` writes them."""
    print(f"tactile-run: {msg}", file=sys.stderr, flush=True)


__all__ = ["PEN_POLL_S", "Printer", "Runner", "Summary", "check_device", "post_processor",
           "read_pen", "replay", "say", "wait_for_pen"]
