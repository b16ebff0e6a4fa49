"""The simulated pen on a link: the bytes it sends, with the faults a real cable has.

:class:`PenLink` turns :class:`~tactile.device.sim.simulator.PenSimulator` samples into the wire
format (header at start and every second, samples frames, or CSV lines) and injects faults
deterministically from its seed. The same object feeds the ``sim://`` pyserial URL
(:mod:`tactile.device.sim.protocol_sim`), the pseudo-terminal (``tactile-sim --pty``) and tests.

Fault options (all off by default):

* ``garbage=P``: before each frame, with probability P, 1..32 random non-zero bytes;
* ``flip=P``: each byte has one random bit flipped with probability P;
* ``drop=P``: each samples frame is lost with probability P (the pen's counter moves on);
* ``stall=T:D``: at stream second T the link goes silent for D seconds; the samples of those
  D seconds are lost (the pen keeps counting), as when a USB hub stalls;
* ``unplug=T:D``: at stream second T the port raises as a vanished USB serial device does and
  cannot be reopened for D seconds; the pen then restarts (sequence from 0, header first) at
  stream second T + D (the hand went on moving);
* ``stall_every=P``, ``unplug_every=P``: repeat the stall (the unplug) every P stream seconds
  after T. The schedule belongs to the stream: a replug continues it (a stall or unplug due
  while the pen was unplugged is skipped, the pen being off), and the random faults continue
  from where they were rather than repeating from the seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from urllib.parse import parse_qsl

import numpy as np

from tactile.device.protocol.codec import encode_header, encode_samples
from tactile.device.sim.simulator import TEXTURES, PenSimulator
from tactile.errors import ConfigError


@dataclass(frozen=True)
class LinkConfig:
    """Everything ``sim://?...`` accepts; unknown keys and bad values are errors."""

    texture: str = "paper"
    seed: int = 0
    rate: float = 100.0  # Hz
    speed: float = 1.0  # x real time; math.inf = as fast as the reader reads ("max")
    seconds: float = math.inf  # the pen stops sending after this much stream time
    per_frame: int = 1  # samples per frame
    format: str = "binary"  # or "csv": a names line, then one line per sample in its units
    garbage: float = 0.0
    flip: float = 0.0
    drop: float = 0.0
    stall: tuple[float, float] | None = None
    unplug: tuple[float, float] | None = None
    stall_every: float = 0.0  # stream seconds between stalls after the first (0: once)
    unplug_every: float = 0.0  # stream seconds between unplugs after the first (0: once)

    def __post_init__(self) -> None:
        if self.texture not in TEXTURES:
            raise ConfigError(f"texture {self.texture!r}: must be one of {', '.join(TEXTURES)}")
        if not (10 <= self.rate <= 10_000):  # the simulator's range
            raise ConfigError(f"rate {self.rate!r}: must be in [10, 10000] Hz")
        if self.seed < 0:
            raise ConfigError(f"seed {self.seed!r}: must be >= 0")
        if not self.speed > 0:
            raise ConfigError(f"speed {self.speed!r}: must be > 0 or 'max'")
        if not 1 <= self.per_frame <= 32:
            raise ConfigError(f"per_frame {self.per_frame!r}: must be 1..32")
        if self.format not in ("binary", "csv"):
            raise ConfigError(f"format {self.format!r}: must be binary or csv")
        for name in ("garbage", "flip", "drop"):
            p = getattr(self, name)
            if not 0 <= p <= 1:
                raise ConfigError(f"{name}={p!r}: must be a probability in [0, 1]")
        if not self.seconds > 0:
            raise ConfigError(f"seconds {self.seconds!r}: must be > 0")
        for name, fault in (("stall", self.stall), ("unplug", self.unplug)):
            every = getattr(self, f"{name}_every")
            if every and (fault is None or not every > fault[1]):
                raise ConfigError(f"{name}_every={every!r}: needs {name}=T:D and must be > D")
            if not (math.isfinite(every) and every >= 0):
                raise ConfigError(f"{name}_every={every!r}: must be >= 0 seconds")

    @classmethod
    def from_query(cls, query: str) -> LinkConfig:
        """Parse ``texture=paper&seed=3&speed=max&unplug=2:0.5`` (the part after ``?``)."""
        kinds = {f.name: f.type for f in fields(cls)}
        kw: dict = {}
        for key, value in parse_qsl(query, keep_blank_values=True, strict_parsing=False):
            if key not in kinds:
                raise ConfigError(f"sim:// option {key!r} unknown; allowed: {', '.join(kinds)}")
            if key in kw:  # the last one winning would ignore the first in silence
                raise ConfigError(f"sim:// option {key!r} given twice")
            try:
                kw[key] = _convert(key, value)
            except ValueError:
                raise ConfigError(f"sim:// option {key}={value!r}: not a valid value") from None
        return cls(**kw)


def _convert(key: str, value: str):
    if key in ("texture", "format"):
        return value
    if key in ("seed", "per_frame"):
        return int(value)
    if key in ("stall", "unplug"):  # T:D
        t, d = value.split(":")
        t, d = float(t), float(d)
        if not (math.isfinite(t) and math.isfinite(d) and t >= 0 and d > 0):
            raise ValueError
        return (t, d)
    if key == "speed" and value == "max":
        return math.inf
    return float(value)


@dataclass
class Injected:
    """What the link did to the stream, to compare with what a receiver counted."""

    frames: int = 0
    samples: int = 0  # samples the pen produced (sent or not)
    dropped_frames: int = 0
    dropped_samples: int = 0
    garbage_bytes: int = 0
    flipped_bytes: int = 0
    stalled_samples: int = 0
    stalls: int = 0
    unplugs: int = 0
    unplugged_samples: int = 0  # not made while the pen was unplugged


def _schedule(fault: tuple[float, float] | None, every: float, after: float) -> float:
    """Stream time of the first stall/unplug of ``fault`` (T:D, repeated every ``every``)
    at or after ``after`` (inf when there is none)."""
    if fault is None:
        return math.inf
    t = fault[0]
    if t >= after - 1e-9:
        return t
    if not every:
        return math.inf
    return t + math.ceil((after - t - 1e-9) / every) * every


class PenLink:
    """Bytes the pen sends, produced on demand, with faults. Deterministic given the config.

    Args:
        config: the link settings.
        restart_at_s: start the pen at this stream time (after an unplug the pen reboots: its
            counter restarts at 0 while the hand, and so the simulated motion, went on).
        trace: record the fate of every sample (:attr:`delivered`) and where intact headers
            went out (:attr:`headers`): the ground truth a receiver is checked against.
    """

    def __init__(self, config: LinkConfig, restart_at_s: float = 0.0,
                 trace: bool = False) -> None:
        self.config = config
        self.sim = PenSimulator(config.texture, config.seed, config.rate)
        self.rng = np.random.default_rng([config.seed, 0x11AC])
        self.injected = Injected()
        self.info = self.sim.info
        self._scale = np.array([ch.scale for ch in self.info.channels])
        self._offset = np.array([ch.offset for ch in self.info.channels])
        self.seq = 0  # the pen's sample counter since it (re)started
        # with trace: per stream sample, 1 = sent in an intact frame; stream indices of the
        # intact headers
        self.delivered: bytearray | None = bytearray() if trace else None
        self.headers: list[int] = []
        self._next_stall = _schedule(config.stall, config.stall_every, 0.0)
        self._next_unplug = _schedule(config.unplug, config.unplug_every, 0.0)
        self._next_header = 0
        self._skip_to(restart_at_s)

    def _skip_to(self, at_s: float) -> None:
        """Advance the motion, not the counter, to stream time ``at_s``; faults scheduled in
        between do not happen (the pen is off)."""
        skip = int(min(max(0, round(at_s * self.config.rate) - self.sim.n_read), self._left()))
        self.injected.unplugged_samples += skip if self.sim.n_read else 0
        while skip > 0:
            k = min(skip, 4096)
            self.sim.read(k)
            self._mark(k, 0)
            skip -= k
        self._next_stall = _schedule(self.config.stall, self.config.stall_every,
                                     self.stream_time)
        self._next_unplug = _schedule(self.config.unplug, self.config.unplug_every,
                                      self.stream_time)

    def _mark(self, n: int, value: int) -> None:
        if self.delivered is not None:
            self.delivered += bytes([value]) * n

    def unplug_due(self) -> float | None:
        """The unplug's duration D when one is due now (it is then counted), else None."""
        cfg = self.config
        if self.stream_time < self._next_unplug - 1e-9:
            return None
        self._next_unplug = (self._next_unplug + cfg.unplug_every if cfg.unplug_every
                             else math.inf)
        self.injected.unplugs += 1
        return cfg.unplug[1]

    def restart(self, at_s: float) -> None:
        """The pen reboots after an unplug, at stream time ``at_s``: counter from 0, header
        first; the fault schedule and the random faults go on."""
        self.seq = 0
        self._next_header = 0
        self._skip_to(at_s)

    @property
    def stream_time(self) -> float:
        """Seconds of samples produced since the simulation began."""
        return self.sim.n_read / self.config.rate

    @property
    def finished(self) -> bool:
        return self.stream_time >= self.config.seconds - 1e-9

    def _left(self) -> float:
        """Samples the pen still makes before ``seconds`` (inf without an end)."""
        cfg = self.config
        if not math.isfinite(cfg.seconds):
            return math.inf
        return max(0, round(cfg.seconds * cfg.rate) - self.sim.n_read)

    def _whole_frames(self, n: int) -> int:
        """``n`` rounded down to whole frames of ``per_frame``, except for the stream's last
        frame, which may be short: frames do not depend on how the reader asks."""
        if math.isfinite(self._next_unplug):  # the pen sends nothing past its unplug
            n = min(n, max(0, round(self._next_unplug * self.config.rate) - self.sim.n_read))
        left = self._left()
        if n >= left:
            return int(left)
        return n - n % self.config.per_frame

    def produce(self, n: int) -> bytes:
        """The bytes for up to ``n`` more samples, in whole frames of ``per_frame`` (so fewer
        when ``n`` is not a multiple of it, at the end of ``seconds``, or at a stall: the call
        ends where the silence begins). A reader asks again for what is due, as the ``sim://``
        port and the pty server do: the bytes and the faults are the same whatever the sizes
        asked."""
        cfg = self.config
        n = self._whole_frames(n)
        out = bytearray()
        while n > 0:
            if self.stream_time >= self._next_stall - 1e-9:
                # the stall's samples count against `seconds` too: none past the stream's end
                lost = int(min(round(cfg.stall[1] * cfg.rate), self._left()))
                self.sim.read(lost)
                self._mark(lost, 0)
                self.seq += lost
                self.injected.samples += lost
                self.injected.stalled_samples += lost
                self.injected.stalls += 1
                self._next_stall = (self._next_stall + cfg.stall_every if cfg.stall_every
                                    else math.inf)
                break  # what follows the silence comes after it: the reader asks again
            if self.seq >= self._next_header:  # header at start, then once a second
                if cfg.format == "binary":
                    out += self._frame(encode_header(self.info), 0)
                elif self.seq == 0:  # CSV: the names line once, as hobby sketches print it
                    out += self._frame((",".join(self.info.channel_names) + "\n").encode(),
                                       0, faults=False)
                self._next_header = self.seq + max(1, round(cfg.rate))
            k = min(n, cfg.per_frame)
            raw = self.sim.read(k)
            t_us = round(self.sim.n_read * 1e6 / cfg.rate) - round(k * 1e6 / cfg.rate)
            self.injected.samples += k
            self.injected.frames += 1
            if cfg.drop and self.rng.random() < cfg.drop:
                self.injected.dropped_frames += 1
                self.injected.dropped_samples += k
                self._mark(k, 0)
            elif cfg.format == "csv":  # values in their units, as PROTOCOL.md asks of CSV
                vals = raw * self._scale + self._offset
                out += self._frame("".join(",".join(f"{v:.7g}" for v in r) + "\n"
                                           for r in vals).encode(), k)
            else:
                out += self._frame(encode_samples(self.seq, t_us, raw), k)
            self.seq += k
            n -= k
        return bytes(out)

    def _frame(self, data: bytes, k: int, faults: bool = True) -> bytes:
        """A frame of ``k`` samples (0: a header) with its faults; traced as intact unless a bit
        of it flipped (garbage before a frame is resynchronised over)."""
        data, intact = self._fault(data) if faults else (data, True)
        if self.delivered is not None:
            first = self.sim.n_read - k
            if k:
                self._mark(k, 1 if intact else 0)
            elif intact:
                self.headers.append(first)
        return data

    def _fault(self, data: bytes) -> tuple[bytes, bool]:
        """``data`` with garbage before it and bits flipped, and whether the frame itself
        (not the garbage) came through intact."""
        cfg = self.config
        intact, size = True, len(data)
        if cfg.garbage and self.rng.random() < cfg.garbage:
            g = self.rng.integers(1, 256, int(self.rng.integers(1, 33))).astype(np.uint8)
            self.injected.garbage_bytes += len(g)
            data = g.tobytes() + data
        if cfg.flip:
            hit = self.rng.random(len(data)) < cfg.flip
            if hit.any():
                arr = np.frombuffer(data, np.uint8).copy()
                bits = self.rng.integers(0, 8, int(hit.sum()))
                arr[hit] ^= (1 << bits).astype(np.uint8)
                self.injected.flipped_bytes += int(hit.sum())
                data = arr.tobytes()
                intact = not hit[len(data) - size :].any()
        return data, intact
