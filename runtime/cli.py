"""``tactile-run``: read the pen, print one label per window, keep going.

    tactile-run --model model.onnx --port /dev/ttyACM0
    tactile-run --model model.onnx --port "sim://?texture=paper&seed=3"
    tactile-run --model model.onnx --replay data/paper-....csv      # offline, as fast as it can

Labels and events (gaps, stalls, reconnects) go to stdout (JSON Lines by default; ``--format
text|csv``), diagnostics to stderr: a status line every few seconds, a line for each stall and
reconnection, and a summary at the end. Exit codes:
0 stopped cleanly (SIGINT/SIGTERM, end of replay or of ``--seconds``), 1 bad arguments, 2 port
cannot be opened or no pen found, 3 the model or the device does not honour the contract.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import signal
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import tactile.device  # noqa: F401  (registers sim://)
from tactile.cli import Parser, add_debug, add_port_options, float_in, int_in, run, started
from tactile.device.link import Connection, LinkSettings, Reconnected, Stall, find_port, keep_trying
from tactile.device.protocol import DeviceInfo, Gap, Header, Samples, StreamDecoder
from tactile.errors import ModelContractError, RecordingError
from tactile.runtime.model import Model
from tactile.runtime.stream import Label, Smoother, Stream
from tactile.runtime.units import to_units

FORMATS = ("jsonl", "text", "csv")
CPUS = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@dataclass
class Summary:
    windows: int = 0
    labels: Counter = field(default_factory=Counter)
    gaps: int = 0
    reconnects: int = 0
    stalls: int = 0
    before_header: int = 0  # samples that arrived before the first header (not classified)
    started: float = field(default_factory=time.monotonic)
    first_label_s: float | None = None

    def to_dict(self, decoder_stats: dict) -> dict:
        return {
            "windows": self.windows,
            "labels": dict(self.labels),
            "gaps": self.gaps,
            "reconnects": self.reconnects,
            "stalls": self.stalls,
            "samples_before_header": self.before_header,
            "first_label_s": self.first_label_s,
            "seconds": round(time.monotonic() - self.started, 3),
            "decoder": decoder_stats,
        }


class Printer:
    """Writes labels and events in the chosen format, flushing each line."""

    def __init__(self, fmt: str, classes: tuple[str, ...], out=None) -> None:
        # sys.stdout as it is now, not as it was at import (contextlib.redirect_stdout works)
        out = sys.stdout if out is None else out
        self.fmt, self.classes, self.out = fmt, classes, out
        if fmt == "csv":  # an event is a row of its own: its seq (if any) and `event` filled
            self._csv = csv.writer(out, lineterminator="\n")  # quotes what needs quoting
            self._row(["t", "seq", "label", "p", "latency_ms", "smoothed", *classes, "event"])

    def _row(self, cells: list) -> None:
        self._csv.writerow(cells)
        self.out.flush()

    def label(self, lab: Label) -> None:
        if self.fmt == "csv":
            self._row([f"{lab.t_us / 1e6:.6f}", lab.seq, lab.label, f"{lab.probability:.6f}",
                       f"{lab.latency_ms:.3f}", lab.smoothed or "",
                       *(f"{lab.probabilities[c]:.6f}" for c in self.classes), ""])
            return
        if self.fmt == "jsonl":
            line = json.dumps(lab.to_dict())
        else:
            smooth = f" ({lab.smoothed})" if lab.smoothed else ""
            line = f"{lab.t_us / 1e6:10.2f} s  #{lab.seq:<8d} {lab.label}{smooth}  " \
                   f"p={lab.probability:.3f}"
        print(line, file=self.out, flush=True)

    def event(self, kind: str, **fields) -> None:
        """Gaps, stalls and reconnects: a JSON object in jsonl mode, a row with the `event`
        column filled in csv mode, a ``#`` comment line in text mode."""
        if self.fmt == "jsonl":
            print(json.dumps({"event": kind, **fields}), file=self.out, flush=True)
        elif self.fmt == "csv":
            what = " ".join([kind, *(f"{k}={v}" for k, v in fields.items() if k != "seq")])
            self._row(["", fields.get("seq", ""), *[""] * (len(self.classes) + 4), what])
        else:
            print(f"# {kind} " + " ".join(f"{k}={v}" for k, v in fields.items()),
                  file=self.out, flush=True)


def check_device(model: Model, info: DeviceInfo) -> None:
    """The device's header must give the model's channels, in order, in its units, at its rate
    (a CSV-line device, which declares neither units nor rate, is taken in the model's)."""
    want = model.contract.channels
    got = info.channel_names
    if got != want:
        raise ModelContractError(
            f"device channels {list(got)} do not match the model's {list(want)} (names and order)"
        )
    got_units = tuple(ch.unit for ch in info.channels)
    if info.device == "csv" and not any(got_units):  # a CSV device: no units, no rate
        _say(f"CSV device: its values are taken in the model's units "
             f"{list(model.contract.units)}, at the model's {model.contract.sample_rate_hz:g} Hz")
    elif got_units != model.contract.units:
        raise ModelContractError(
            f"device units {list(got_units)} do not match the model's "
            f"{list(model.contract.units)}"
        )
    if not math.isclose(info.sample_rate_hz, model.contract.sample_rate_hz, rel_tol=1e-3):
        raise ModelContractError(
            f"device rate {info.sample_rate_hz:g} Hz does not match the model's "
            f"{model.contract.sample_rate_hz:g} Hz"
        )


class Runner:
    """Decoder events -> stream -> labels. No I/O of its own beyond the printer."""

    def __init__(self, model: Model, stream: Stream, printer: Printer, summary: Summary):
        self.model, self.stream, self.printer, self.summary = model, stream, printer, summary
        self.info: DeviceInfo | None = None
        self.tap: Callable[[object], None] | None = None  # sees each decoder event (--serve)

    def handle(self, events: list) -> None:
        """Decoder events, and the link's (:mod:`~tactile.device.connection`), in order."""
        for ev in events:
            if self.tap is not None:
                self.tap(ev)
            if isinstance(ev, Reconnected):  # the same pen, restarted: a new window
                self.summary.reconnects += 1
                self.stream.reset()
                self.printer.event("reconnect", port=ev.port)
            elif isinstance(ev, Stall):
                self.summary.stalls += 1
                self.printer.event("stall", seconds=ev.seconds)
            elif isinstance(ev, Header):
                check_device(self.model, ev.info)
                if ev.changed:
                    self.stream.reset()
                self.info = ev.info
            elif isinstance(ev, Gap):
                self.summary.gaps += 1
                self.stream.gap()
                self.printer.event("gap", seq=ev.seq, missing=ev.missing, reason=ev.reason)
            elif isinstance(ev, Samples):
                if self.info is None:  # no header yet: we cannot check or scale these samples
                    self.summary.before_header += len(ev.raw)
                    continue
                period = 1e6 / self.info.sample_rate_hz
                self.stream.accept(to_units(self.info, ev.raw), ev.seq, ev.t_us, period)
                while self.stream.ready():
                    lab = self.stream.classify()
                    self.summary.windows += 1
                    self.summary.labels[lab.label] += 1
                    if self.summary.first_label_s is None:
                        self.summary.first_label_s = round(
                            time.monotonic() - self.summary.started, 3)
                    self.printer.label(lab)


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
    _say("no likely pen attached; waiting for one")
    port = keep_trying(lambda: find_port(wait=True), stop, _say, "a likely pen", deadline,
                       status_every, (PEN_POLL_S, PEN_POLL_S))
    if port is None and not stop["flag"]:
        _say(f"no pen attached after {time.monotonic() - start:.1f} s (--seconds); stopping")
    return port


def serve(args: argparse.Namespace, runner: Runner, decoder: StreamDecoder,
          stop: dict) -> None:
    """The serial loop: read, decode, classify, through a
    :class:`~tactile.device.connection.Connection` (it reconnects to the same pen only)."""
    summary = runner.summary
    deadline = summary.started + args.seconds
    settings = LinkSettings(args.port, args.baud, auto=getattr(args, "auto", False),
                            wait=args.wait, stall_timeout=args.stall_timeout,
                            status_every=args.status_every)
    with Connection(settings, decoder, stop, _say, deadline) as conn:
        if not conn.open():
            return
        last_status = time.monotonic()
        while not stop["flag"] and time.monotonic() < deadline:
            chunk = conn.read()
            if chunk is None:  # stopped, or out of time, while the pen was away
                break
            runner.handle(chunk.events)
            now = time.monotonic()
            if now - last_status >= args.status_every:
                last_status = now
                _status(runner, decoder, conn.silent_for(now))


def _status(runner: Runner, decoder: StreamDecoder, silent: float | None) -> None:
    """The status line on stderr."""
    summary, st = runner.summary, decoder.stats
    notes = f"  no data for {silent:.0f} s" if silent is not None else ""
    if runner.info is None and summary.before_header:
        notes += f"  no device header yet: {summary.before_header} samples left unclassified"
    _say(f"windows {summary.windows}  gaps {st.gaps} (lost {st.samples_lost})  "
         f"crc {st.crc_errors}  malformed {st.malformed}  "
         f"rejected {st.csv_rejected}  discarded {st.bytes_discarded} B  "
         f"reconnects {summary.reconnects}{notes}")


def replay(path: Path, runner: Runner, stop: dict, deadline: float = math.inf,
           clock: Callable[[], float] = time.monotonic) -> None:
    """Run a recorded take through the same stream, as fast as possible, until its end, a stop
    or ``deadline`` (on ``clock``, from ``--seconds``: the rest of the take is left out, with a
    line that says where it stopped)."""
    from tactile.device.recordings import read_take

    take = read_take(path)
    if len(take.seq) == 0:
        raise RecordingError(f"{path}: the take holds no samples")
    if take.truncated:
        _say(f"{path}: its last row was cut short (the recording stopped mid-write); "
             "it is left out")
    runner.handle([Header(take.info)])
    for a, b in take.segments():
        if stop["flag"]:
            break
        if a > 0:
            runner.handle([Gap(int(take.seq[a]), int(take.seq[a] - take.seq[a - 1] - 1),
                               "recorded")])
        for i in range(a, b, 256):
            if stop["flag"]:
                return
            if clock() >= deadline:
                _say(f"--seconds: stopped before seq {int(take.seq[i])} ({i} of the "
                     f"{len(take.seq)} samples of {path} done)")
                return
            j = min(i + 256, b)
            runner.handle([Samples(int(take.seq[i]), int(take.t_us[i]), take.raw[i:j])])


def _say(msg: str) -> None:
    print(f"tactile-run: {msg}", file=sys.stderr, flush=True)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="tactile-run",
        description="Read the pen, print one label per window (stdout), keep going.",
        epilog="exit codes: 0 stopped cleanly, 1 bad arguments, 2 port cannot be opened or no "
        "pen found, 3 model or device does not honour the contract",
    )
    p.add_argument("--model", required=True, type=Path, help="the .onnx file from tactile-export")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--port", help="device path or pyserial URL (sim://, socket://, ...); "
                     "default: the one likely pen attached")
    src.add_argument("--replay", type=Path, metavar="TAKE", help="a recorded take (.csv)")
    p.add_argument("--wait", action="store_true",
                   help="if the port is absent at start, wait for it (as after an unplug) "
                   "instead of exiting with code 2; without --port, wait until one likely pen "
                   "is attached; for a service started before the pen is plugged in")
    p.add_argument("--hop", type=int_in(1),
                   help="samples between windows (default: the model's)")
    p.add_argument("--format", choices=FORMATS, default="jsonl",
                   help="jsonl (default): one JSON object per window or event; csv: a header, "
                   "one row per window or event; text: for people")
    p.add_argument("--smooth", type=int_in(1), default=1, metavar="K",
                   help="also report the label averaged over the last K windows")
    p.add_argument("--hysteresis", type=float_in(0.0, 1.0, low_open=False, high_open=True),
                   default=0.0, metavar="MARGIN",
                   help="the smoothed label changes only when beaten by MARGIN")
    p.add_argument("--threads", type=int_in(1, CPUS), default=1,
                   help=f"onnxruntime threads, at most the {CPUS} cores (default 1)")
    p.add_argument("--status-every", type=float_in(0.0), default=5.0,
                   help="status line period, s")
    add_port_options(p, "the channels, labels and link")
    add_debug(p)
    return p


def _main(args: argparse.Namespace) -> int:
    model = Model(args.model, threads=args.threads)
    c = model.contract
    hop = c.hop if args.hop is None else args.hop
    smoother = Smoother(args.smooth, args.hysteresis) if args.smooth > 1 or args.hysteresis \
        else None
    stream = Stream.for_model(model, hop, smoother)
    summary = Summary()
    runner = Runner(model, stream, Printer(args.format, c.classes), summary)
    decoder = StreamDecoder(csv_rate_hz=c.sample_rate_hz)
    live = None
    if args.serve:
        from tactile.runtime.serve import serve_runner

        live = serve_runner(args.serve, runner, decoder, _say)
    try:
        _read(args, runner, decoder, summary)
    finally:  # the page gets its end, stderr its last line, whatever stopped the run
        if live is not None:
            live.close()
    print("tactile-run: summary " + json.dumps(summary.to_dict(decoder.stats.as_dict())),
          file=sys.stderr, flush=True)
    return 0


def _read(args: argparse.Namespace, runner: Runner, decoder: StreamDecoder, summary: Summary
          ) -> None:
    """Until stopped: the replay, or the pen (found, or waited for, first)."""
    stop = {"flag": False}
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *_: stop.__setitem__("flag", True))
    early = started()  # after our handlers are in place: no signal falls between the two
    if early:
        _say(f"stopped by {early} while starting")
    elif args.replay:
        replay(args.replay, runner, stop, summary.started + args.seconds)
    else:
        args.auto = args.port is None  # found by auto-detection: after an unplug, look again
        if args.port is None:
            args.port = wait_for_pen(stop, summary.started + args.seconds, args.status_every) \
                if args.wait else find_port()
        if args.port is not None:  # None: stopped while waiting for a pen
            serve(args, runner, decoder, stop)


def main(argv: list[str] | None = None) -> int:
    return run("tactile-run", _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
