"""The recorder behind ``tactile-record``: read a pen and write labelled takes.

Progress and diagnostics go to stderr. Ctrl-C
or SIGTERM finishes the take cleanly; a killed recorder leaves a readable take holding every
sample that had reached it after the pen's header, and every gap among them. A vanished port is
reopened with backoff and the take goes on after a ``restart`` gap. A header change (another
pen, another layout) starts a new take.
"""

from __future__ import annotations

import math
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import tactile.device  # noqa: F401  (registers sim://)
from tactile.cli import started
from tactile.device.link.connection import Connection, LinkSettings, Lost, Reconnected
from tactile.device.protocol.decoder import Gap, Header, Samples, StreamDecoder
from tactile.device.protocol.info import DeviceInfo
from tactile.device.recordings.take import check_joins, check_label_joins
from tactile.device.recordings.writer import TakeWriter
from tactile.errors import DeviceError, RecordingError

MAX_EARLY = 100_000
"""Samples held while waiting for the device's first header (a binary device's samples cannot
be written before it says what they are): 1000 s of a 100 Hz pen, which sends its header every
second; at most 1.6 MB of counts for 8 channels. One more is an error (exit 2) that says none
of them was recorded."""


@dataclass
class RecordResult:
    takes: list[Path] = field(default_factory=list)
    samples: int = 0
    gaps: int = 0  # gap lines written into the takes
    samples_lost: int = 0  # the samples those gaps say are missing
    reconnects: int = 0
    stats: dict = field(default_factory=dict)
    stopped_by: str | None = None  # the signal that ended the recording, if one did
    unrecorded: int = 0  # samples that came before any device header: not in any take


def samples_for(seconds: float, rate_hz: float) -> float:
    """The samples ``seconds`` of data at ``rate_hz`` hold: the whole number that covers them
    (1.1 s at 100 Hz: 110; 0.001 s: 1), with float error in ``seconds * rate_hz`` forgiven
    (2.3 * 100 is 229.99999999999997: 230); inf stays inf. A fraction of a sample as the goal
    could never be reached (the take stopped growing and the command went on for ever)."""
    n = seconds * rate_hz
    if not math.isfinite(n):  # inf, or more than a float holds (1e307 s): no end
        return math.inf
    return float(math.ceil(round(n, 6)))


class Recorder:
    """Decoder events -> take files. Separate from the port loop so tests can drive it."""

    def __init__(
        self, out: Path, label: str, source: str, extra: dict | None = None,
        seconds: float = math.inf,
    ) -> None:
        check_label_joins(out, label)  # before the port opens: the label is known now
        self.out, self.label, self.source, self.extra = out, label, source, extra
        self.seconds = seconds
        self.max_samples = math.inf  # set from the device's rate when its header arrives
        self.writer: TakeWriter | None = None
        self.early: list[Samples | Gap] = []  # before the first header: kept, in order
        self.early_samples = 0  # the samples in it (at most MAX_EARLY)
        self.unfit = 0  # samples whose width is not the header's (this take)
        self.result = RecordResult()

    def handle(self, events: list, decoder: StreamDecoder) -> int:
        """Write the decoder's events (a link's :class:`~tactile.device.link.connection.Lost`
        flushes the take, a :class:`~tactile.device.link.connection.Reconnected` is counted);
        returns the number of samples written."""
        written = 0
        for ev in events:
            if isinstance(ev, Header):
                if self.writer is not None and ev.changed:
                    self._close(decoder)
                if self.writer is None:
                    self.max_samples = samples_for(self.seconds, ev.info.sample_rate_hz)
                    self._open(ev.info)
                    for e in self.early:
                        written += self._put(e)
                    self.early.clear()
                    self.early_samples = 0
            elif isinstance(ev, Lost):
                if self.writer is not None:
                    self.writer.flush()
            elif isinstance(ev, Reconnected):
                self.result.reconnects += 1
                if self.early_samples:  # whose header they were is now beyond knowing
                    self._unrecorded("the port was lost before the device's header came")
            elif not isinstance(ev, (Samples, Gap)):
                continue
            elif self.writer is None:
                self._hold(ev)
            else:
                written += self._put(ev)
        return written

    def _hold(self, ev: Samples | Gap) -> None:
        """Keep ``ev`` until the first header, at most :data:`MAX_EARLY` samples."""
        n = len(ev.raw) if isinstance(ev, Samples) else 0
        if self.early_samples + n > MAX_EARLY or len(self.early) >= MAX_EARLY:
            self._give_up_early(n)
            raise DeviceError(
                f"no device header in the first {self.result.unrecorded} samples: none of them "
                "is recorded (a binary pen sends its header every second)")
        self.early.append(ev)
        self.early_samples += n

    def _give_up_early(self, more: int = 0) -> int:
        """Give up the samples held for want of a header (and ``more`` that came with the last
        event): counted in ``result.unrecorded``; returns how many."""
        n = self.early_samples + more
        self.early.clear()
        self.early_samples = 0
        self.result.unrecorded += n
        return n

    def _unrecorded(self, why: str) -> None:
        """Give up the samples held for want of a header: counted, and said."""
        n = self._give_up_early()
        _say(f"tactile-record: {n} sample(s) that came before any device header are not "
             f"recorded: {why}", progress=True)

    def _put(self, ev: Samples | Gap) -> int:
        room = self.max_samples - self.result.samples
        if room <= 0:
            return 0
        if isinstance(ev, Gap):
            self._gap(ev)
            return 0
        raw = ev.raw[: int(min(room, len(ev.raw)))]
        width = len(self.writer.info.channels)
        if raw.ndim != 2 or raw.shape[1] != width:
            # not what the header describes (frames from before it, another firmware): no
            # column can hold them; the take says that many samples are missing there
            self.unfit += len(raw)
            if self.unfit == len(raw):
                _say(f"tactile-record: {len(raw)} sample(s) of {raw.shape[-1]} channels do not "
                     f"fit the header's {width}: left out, recorded as a 'rejected' gap",
                     progress=True)
            self._gap(Gap(ev.seq + len(raw), len(raw), "rejected"))
            return 0
        self.writer.write(ev.seq, ev.t_us, raw)
        self.result.samples += len(raw)
        return len(raw)

    def _gap(self, gap: Gap) -> None:
        self.writer.gap(gap)
        self.result.gaps += 1
        self.result.samples_lost += gap.missing

    def _open(self, info: DeviceInfo) -> None:
        mine = {p.stem for p in self.result.takes}
        try:
            check_joins(self.out, mine, info)
        except RecordingError as e:
            if not mine:  # the first header: nothing is written yet, so stop before a take
                self._give_up_early()
                raise RecordingError(f"{e}; nothing recorded") from None
            # another device mid-recording: its take is written (no data is given up), and
            # the user is told that it will not load with the folder's others
            _say(f"tactile-record: warning: {e}: the new take is written all the same; move "
                 "it or the others to a folder of their own", progress=True)
        self.writer = TakeWriter(self.out, self.label, info, self.source, extra=self.extra)
        self.unfit = 0
        self.result.takes.append(self.writer.csv_path)

    def _close(self, decoder: StreamDecoder, complete: bool = True) -> None:
        """Close the take: complete unless told otherwise or a write failed."""
        if self.writer is not None:
            writer, self.writer = self.writer, None
            writer.set_decoder_stats(decoder.stats)
            writer.close(complete)

    def close(self, decoder: StreamDecoder, complete: bool = True) -> None:
        """Close the take (``complete``: False when the recording ended on an error). Samples
        still held for want of a header are counted in ``result.unrecorded``. Rows the decoder
        still holds back (a CSV board's, waiting for its names line) are written first."""
        try:
            self.handle(decoder.finish(), decoder)
        finally:
            self._close(decoder, complete)
        self._give_up_early()
        self.result.stats = decoder.stats.as_dict()


def record(
    port: str,
    label: str,
    out: Path,
    seconds: float = math.inf,
    baud: int = 115200,
    csv_rate_hz: float = 100.0,
    stall_timeout: float = 2.0,
    progress: bool = True,
    auto: bool = False,
    extra: dict | None = None,
) -> RecordResult:
    """Record until ``seconds`` of samples are written, or SIGINT/SIGTERM. ``auto``: ``port``
    was auto-detected, and after an unplug the pen is looked for among the likely pens too (it
    may come back under another name). ``extra``: more keys for each take's JSON (``user``,
    ``session``...)."""
    rec = Recorder(out, label, port, extra=extra, seconds=seconds)
    decoder = StreamDecoder(csv_rate_hz=csv_rate_hz)
    stop = {"flag": False}

    def on_signal(signum, frame):  # finish the take, do not die mid-write
        stop["flag"] = True
        rec.result.stopped_by = rec.result.stopped_by or signal.Signals(signum).name

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    early = started()  # after our handlers are in place: no signal falls between the two
    if early:  # a signal while the command was starting: no port, no take
        stop["flag"] = True
        rec.result.stopped_by = rec.result.stopped_by or early
    settings = LinkSettings(port, baud, auto=auto, stall_timeout=stall_timeout, poll=0.1)
    conn = Connection(settings, decoder, stop, lambda m: _say(f"tactile-record: {m}", progress))
    try:
        if not stop["flag"]:
            conn.open()
        last_report = time.monotonic()
        for chunk in conn.chunks():  # until stopped, even while the pen is away
            rec.handle(chunk.events, decoder)
            now = time.monotonic()
            if progress and now - last_report >= 1.0:
                last_report = now
                rate = decoder.info.sample_rate_hz if decoder.info else csv_rate_hz
                _progress(label, rec.result.samples / rate, seconds, decoder,
                          conn.silent_for(now), rec.early_samples)
            if rec.result.samples >= rec.max_samples:
                break
    finally:
        try:  # (closing can raise: the rows a CSV board's names line was awaited for)
            rec.close(decoder, complete=sys.exc_info()[0] is None)  # an error: not complete
        finally:
            conn.close()
            for s, h in old.items():
                signal.signal(s, h)
    return rec.result


def _progress(
    label: str, done_s: float, total_s: float, decoder: StreamDecoder, silent: float | None,
    held: int = 0,
) -> None:
    st = decoder.stats
    total = "" if math.isinf(total_s) else f" / {total_s:.0f} s"
    quiet = "" if silent is None else f"  no data for {silent:.1f} s"
    if held:
        quiet += f"  no device header yet: {held} samples held"
    _say(
        f"[{label}] {done_s:6.1f} s{total}  samples {st.samples}  gaps {st.gaps} "
        f"(lost {st.samples_lost})  errors {st.errors}{quiet}",
        progress=True,
    )


def _say(msg: str, progress: bool) -> None:
    if progress:
        print(msg, file=sys.stderr, flush=True)


__all__ = ["record", "Recorder", "RecordResult", "MAX_EARLY"]
