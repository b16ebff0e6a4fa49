"""What the stream decoder hands out: samples, headers and gaps, in stream order, and the
counters of everything it saw and dropped (:class:`DecoderStats`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tactile.device.protocol.info import DeviceInfo


@dataclass(frozen=True)
class Samples:
    """A run of consecutive samples.

    ``seq`` is the host's sequence number of the first sample: the device's counter unwrapped
    past 2**32 and kept continuous across device restarts. ``t_us`` is the device clock at the
    first sample, unwrapped (in CSV mode, which has no device clock, it is derived from ``seq``
    and the configured rate). ``raw`` is (n, channels): int16 counts from binary frames,
    float64 values from CSV lines.
    """

    seq: int
    t_us: int
    raw: np.ndarray


@dataclass(frozen=True)
class Header:
    """The device described itself; ``changed`` is True when it differs from the previous one."""

    info: DeviceInfo
    changed: bool = False


@dataclass(frozen=True)
class Gap:
    """Samples that should have come before ``seq`` and did not.

    ``reason`` is ``"drop"`` (the device's sequence jumped: ``missing`` samples lost),
    ``"restart"`` (the device rebooted, or the link was re-opened; ``missing`` is unknown, 0),
    ``"rejected"`` (``missing`` CSV rows were unreadable) or ``"unsupported"`` (the device sent a
    header of a protocol version this decoder does not read: its samples are dropped until a
    header it reads; ``missing`` is 0, the samples refused show as a ``drop`` gap when samples
    resume). No window may span a gap. ``detail`` says more, for people (may be empty).
    """

    seq: int
    missing: int
    reason: str
    detail: str = ""


Event = Samples | Header | Gap


@dataclass
class DecoderStats:
    """Counters of everything the decoder saw and everything it dropped."""

    bytes_in: int = 0
    frames: int = 0  # good frames of any type
    samples: int = 0  # samples delivered
    header_frames: int = 0
    header_changes: int = 0
    crc_errors: int = 0  # chunks with the structure of a frame whose CRC failed
    malformed: int = 0  # chunks that are not valid COBS, or frames with an invalid structure
    bytes_discarded: int = 0  # bytes that belonged to no good frame or row
    duplicates: int = 0  # frames dropped because their samples were already delivered
    late: int = 0  # frames dropped because their samples had been reported lost (a drop gap)
    unsupported: int = 0  # header frames of a protocol version this decoder does not read
    refused: int = 0  # samples frames dropped because their device's header was refused
    gaps: int = 0
    samples_lost: int = 0
    restarts: int = 0
    csv_rows: int = 0
    csv_rejected: int = 0
    extra: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "extra"}
        d.update(self.extra)
        return d

    @property
    def errors(self) -> int:
        return self.crc_errors + self.malformed + self.csv_rejected + self.unsupported


__all__ = ["Samples", "Header", "Gap", "Event", "DecoderStats"]
