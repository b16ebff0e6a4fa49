"""What a device says about itself: channel names, units, scales and rate (the header frame).

One source of truth for the pen's default channels: :data:`PEN_CHANNELS`.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from tactile.contract_keys import MAX_RATE_HZ
from tactile.errors import FrameError

FLOAT32_MAX = 3.4028234663852886e38
"""The largest float32: a value in units beyond it would become inf in the model's input."""

PROTOCOL_VERSION = 1
# Channels a device description (a recording, a training input) may have: two BioTacs are 88.
# 2048 is more than a CSV line of the wire protocol (4096 bytes) can hold, so every device the
# decoder meets fits. The binary frames keep their own, smaller limit (protocol.WIRE_MAX_CHANNELS).
MAX_CHANNELS = 2048
MAX_NAME = 32  # bytes of UTF-8 in a channel name, unit or device string


@dataclass(frozen=True)
class ChannelSpec:
    """One channel: ``value_in_unit = raw * scale + offset``."""

    name: str
    unit: str
    scale: float = 1.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        for field, text in (("name", self.name), ("unit", self.unit)):
            if not isinstance(text, str) or len(text.encode()) > MAX_NAME:
                raise FrameError(f"channel {field} {text!r}: must be a string of <= {MAX_NAME} B")
        if not self.name:
            raise FrameError("channel name must not be empty")
        if not (math.isfinite(self.scale) and self.scale != 0 and math.isfinite(self.offset)):
            raise FrameError(f"channel {self.name}: scale must be finite, non-zero; offset finite")
        # every int16 count must stay a finite float32 in units (the model's input)
        if 32768 * abs(self.scale) + abs(self.offset) > FLOAT32_MAX:
            raise FrameError(f"channel {self.name}: scale {self.scale:g} and offset "
                             f"{self.offset:g} overflow float32 values")


@dataclass(frozen=True)
class DeviceInfo:
    """The contents of a header frame."""

    sample_rate_hz: float
    channels: tuple[ChannelSpec, ...]
    device: str = "unknown"
    protocol_version: int = PROTOCOL_VERSION

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sample_rate_hz) and 0 < self.sample_rate_hz <= MAX_RATE_HZ):
            raise FrameError(f"sample rate {self.sample_rate_hz!r} Hz: must be in "
                             f"(0, {MAX_RATE_HZ:g}]")
        if not 1 <= len(self.channels) <= MAX_CHANNELS:
            raise FrameError(f"{len(self.channels)} channels: must be 1..{MAX_CHANNELS}")
        names = [c.name for c in self.channels]
        if len(set(names)) != len(names):
            raise FrameError(f"duplicate channel names in {names}")
        if len(self.device.encode()) > MAX_NAME:
            raise FrameError(f"device string {self.device!r}: must be <= {MAX_NAME} bytes")
        if not 0 <= self.protocol_version <= 255:
            raise FrameError(f"protocol version {self.protocol_version}: must be 0..255")

    @property
    def units_unknown(self) -> bool:
        """A CSV-line device (which declares no units: its values are taken in a model's)."""
        return self.device == "csv" and not any(c.unit for c in self.channels)

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.channels)

    def to_dict(self) -> dict:
        return {
            "protocol_version": self.protocol_version,
            "device": self.device,
            "sample_rate_hz": self.sample_rate_hz,
            "channels": [
                {"name": c.name, "unit": c.unit, "scale": c.scale, "offset": c.offset}
                for c in self.channels
            ],
        }

    @classmethod
    def from_dict(cls, d: dict) -> DeviceInfo:
        return cls(
            sample_rate_hz=float(d["sample_rate_hz"]),
            channels=tuple(ChannelSpec(**c) for c in d["channels"]),
            device=str(d.get("device", "unknown")),
            protocol_version=int(d.get("protocol_version", PROTOCOL_VERSION)),
        )


# The pen: a pressure-conductive tip sensor read by a 12-bit ADC (sent twice, as the pen paper
# does), and a 6-axis IMU at +/-2 g (16384 LSB/g) and +/-250 deg/s (131 LSB per deg/s).
# Scales are float32-exact where possible because the header carries them as float32.


def f32(x: float) -> float:
    """``x`` rounded to float32, as a header frame carries it."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


PRESSURE_SCALE = f32(0.01)  # N per ADC count (0..4095 counts -> 0..41 N)
ACCEL_SCALE = f32(1.0 / 16384.0)  # g per count
GYRO_SCALE = f32(1.0 / 131.0)  # deg/s per count
PEN_CHANNELS: tuple[ChannelSpec, ...] = (
    ChannelSpec("pressure_0", "N", PRESSURE_SCALE),
    ChannelSpec("pressure_1", "N", PRESSURE_SCALE),
    ChannelSpec("accel_x", "g", ACCEL_SCALE),
    ChannelSpec("accel_y", "g", ACCEL_SCALE),
    ChannelSpec("accel_z", "g", ACCEL_SCALE),
    ChannelSpec("gyro_x", "deg/s", GYRO_SCALE),
    ChannelSpec("gyro_y", "deg/s", GYRO_SCALE),
    ChannelSpec("gyro_z", "deg/s", GYRO_SCALE),
)
PEN_RATE_HZ = 100.0


def pen_info(sample_rate_hz: float = PEN_RATE_HZ, device: str = "tactile-pen") -> DeviceInfo:
    """The header the pen (real or simulated) sends."""
    return DeviceInfo(sample_rate_hz=sample_rate_hz, channels=PEN_CHANNELS, device=device)
