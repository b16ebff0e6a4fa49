"""The wire protocol: frame layout, COBS byte stuffing, CRC-16, encoder and frame parser.

The byte-level specification is ``device/PROTOCOL.md``; this module is its reference
implementation. The C encoder in ``device/firmware/`` must produce the very same bytes
(``device/firmware/test_vectors.txt`` is shared by both test suites).

A frame on the wire is ``COBS(body + crc16_le(body)) + b"\\x00"`` where ``body`` starts with a
one-byte frame type. All integers are little-endian.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass

import numpy as np

from tactile.device.info import ChannelSpec, DeviceInfo
from tactile.errors import FrameError

DELIMITER = 0x00
TYPE_HEADER = 0x01
TYPE_SAMPLES = 0x02
SEQ_MODULO = 1 << 32  # sequence numbers and device timestamps are u32 and wrap
MAX_SAMPLES_PER_FRAME = 32
# Binary frames carry at most 32 channels (recordings take more: info.MAX_CHANNELS), so that
# a microcontroller's frame buffer stays MAX_BODY bytes; see PROTOCOL.md.
WIRE_MAX_CHANNELS = 32
MAX_BODY = 2560  # largest frame body (type .. last data byte, CRC excluded), in bytes
# (the largest header, 32 channels with 32-byte names and units, is 2409 bytes; the largest
# samples frame, 32 x 32 int16, is 2059)
# Largest encoded frame, delimiter excluded: COBS adds one byte per 254 plus one.
MAX_ENCODED = MAX_BODY + 2 + (MAX_BODY + 2) // 254 + 1

_SAMPLES_HEAD = struct.Struct("<BIIBB")  # type, seq, t_us, n_channels, n_samples
_HEADER_HEAD = struct.Struct("<BBfBB")  # type, version, rate, n_channels, sample format
_CHANNEL_NUMS = struct.Struct("<ff")  # scale, offset
SAMPLE_FORMAT_INT16 = 1


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0).

    ``crc16(b"123456789") == 0x29B1`` (the catalogue check value).
    """
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result contains no zero byte.

    Byte-for-byte the classic encoder (the firmware's C code is the same algorithm): blocks of
    up to 254 non-zero bytes, each led by its length + 1; a full block (code 0xFF) carries no
    implied zero, and a full block that ends the data gets no empty block after it.
    """
    out = bytearray()
    segments = data.split(b"\x00")
    last = len(segments) - 1
    for k, seg in enumerate(segments):
        pos = 0
        while len(seg) - pos >= 254:
            out.append(0xFF)
            out += seg[pos : pos + 254]
            pos += 254
        rest = seg[pos:]
        if rest or k != last or pos == 0:
            out.append(len(rest) + 1)
            out += rest
    return bytes(out)


def cobs_decode(data: bytes) -> bytes | None:
    """Inverse of :func:`cobs_encode`; ``None`` if ``data`` is not a valid encoding."""
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0 or i + code > n:
            return None
        block = data[i + 1 : i + code]
        if 0 in block:
            return None
        out += block
        i += code
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


def frame(body: bytes) -> bytes:
    """Wrap a frame body for the wire: CRC, stuffing, delimiter."""
    if not body or len(body) > MAX_BODY:
        raise FrameError(f"frame body of {len(body)} bytes: must be 1..{MAX_BODY}")
    return cobs_encode(body + struct.pack("<H", crc16(body))) + b"\x00"


def _text(s: str) -> bytes:
    raw = s.encode("utf-8")
    return bytes([len(raw)]) + raw


def header_body(info: DeviceInfo) -> bytes:
    """Body of a header frame (type 0x01)."""
    if len(info.channels) > WIRE_MAX_CHANNELS:
        raise FrameError(f"{len(info.channels)} channels: a header frame carries "
                         f"1..{WIRE_MAX_CHANNELS}")
    parts = [
        _HEADER_HEAD.pack(
            TYPE_HEADER,
            info.protocol_version,
            info.sample_rate_hz,
            len(info.channels),
            SAMPLE_FORMAT_INT16,
        ),
        _text(info.device),
    ]
    for ch in info.channels:
        parts += [_text(ch.name), _text(ch.unit), _CHANNEL_NUMS.pack(ch.scale, ch.offset)]
    return b"".join(parts)


def samples_body(seq: int, t_us: int, raw: np.ndarray) -> bytes:
    """Body of a samples frame (type 0x02).

    Args:
        seq: sequence number of the first sample (the device counts samples), taken mod 2**32.
        t_us: device clock at the first sample in microseconds, taken mod 2**32.
        raw: (n_samples, n_channels) integers in int16 range, sample-major.
    """
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise FrameError(f"samples must be 2-D (n_samples, n_channels), got shape {raw.shape}")
    n, c = raw.shape
    if not (1 <= n <= MAX_SAMPLES_PER_FRAME and 1 <= c <= WIRE_MAX_CHANNELS):
        raise FrameError(
            f"{n} samples x {c} channels: "
            f"must be 1..{MAX_SAMPLES_PER_FRAME} x 1..{WIRE_MAX_CHANNELS}"
        )
    if raw.dtype != np.int16:
        if np.any(raw < -32768) or np.any(raw > 32767):
            raise FrameError("sample values must be in the int16 range")
        raw = raw.astype(np.int16)
    head = _SAMPLES_HEAD.pack(TYPE_SAMPLES, seq % SEQ_MODULO, t_us % SEQ_MODULO, c, n)
    return head + raw.astype("<i2", copy=False).tobytes()


def encode_header(info: DeviceInfo) -> bytes:
    """A complete header frame, ready for the wire."""
    return frame(header_body(info))


def encode_samples(seq: int, t_us: int, raw: np.ndarray) -> bytes:
    """A complete samples frame, ready for the wire."""
    return frame(samples_body(seq, t_us, raw))


# ---------------------------------------------------------------------------------------------
# Parsing (used by the stream decoder; returns None instead of raising on bad bytes)


@dataclass(frozen=True)
class SamplesFrame:
    seq: int  # u32 as sent
    t_us: int  # u32 as sent
    raw: np.ndarray  # (n_samples, n_channels) int16


@dataclass(frozen=True)
class HeaderFrame:
    info: DeviceInfo


def parse_frame(encoded: bytes) -> SamplesFrame | HeaderFrame | None:
    """Parse one encoded frame (delimiter removed). ``None`` if anything is wrong with it."""
    decoded = cobs_decode(encoded)
    if decoded is None or len(decoded) < 3:
        return None
    body, crc = decoded[:-2], decoded[-2:]
    if crc16(body) != int.from_bytes(crc, "little"):
        return None
    return parse_body(body)


def parse_body(body: bytes) -> SamplesFrame | HeaderFrame | None:
    """Parse a CRC-checked frame body. ``None`` if its structure is inconsistent."""
    kind = body[0]
    if kind == TYPE_SAMPLES:
        if len(body) < _SAMPLES_HEAD.size:
            return None
        _, seq, t_us, c, n = _SAMPLES_HEAD.unpack_from(body)
        if not (1 <= c <= WIRE_MAX_CHANNELS and 1 <= n <= MAX_SAMPLES_PER_FRAME):
            return None
        if len(body) != _SAMPLES_HEAD.size + 2 * n * c:
            return None
        raw = np.frombuffer(body, dtype="<i2", offset=_SAMPLES_HEAD.size).reshape(n, c)
        return SamplesFrame(seq, t_us, raw.astype(np.int16))
    if kind == TYPE_HEADER:
        try:
            return HeaderFrame(_parse_header(body))
        except (FrameError, ValueError, IndexError, struct.error, UnicodeDecodeError):
            return None
    return None


def _parse_header(body: bytes) -> DeviceInfo:
    _, version, rate, c, fmt = _HEADER_HEAD.unpack_from(body)
    if not 1 <= c <= WIRE_MAX_CHANNELS:
        raise ValueError(f"{c} channels")
    if fmt != SAMPLE_FORMAT_INT16:
        raise ValueError(f"unknown sample format {fmt}")
    pos = _HEADER_HEAD.size
    device, pos = _read_text(body, pos)
    channels = []
    for _ in range(c):
        name, pos = _read_text(body, pos)
        unit, pos = _read_text(body, pos)
        scale, offset = _CHANNEL_NUMS.unpack_from(body, pos)
        pos += _CHANNEL_NUMS.size
        channels.append(ChannelSpec(name, unit, scale, offset))
    if pos != len(body):
        raise ValueError("trailing bytes in header frame")
    return DeviceInfo(rate, tuple(channels), device, version)


def _read_text(body: bytes, pos: int) -> tuple[str, int]:
    n = body[pos]
    end = pos + 1 + n
    if end > len(body):
        raise ValueError("string runs past the end of the frame")
    return body[pos + 1 : end].decode("utf-8"), end
