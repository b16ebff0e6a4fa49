"""The wire protocol: frame layout, COBS byte stuffing, CRC-16, encoder and frame parser.

The byte-level specification is ``device/PROTOCOL.md``; this module is its reference
implementation. The C encoder in ``device/firmware/`` must produce the very same bytes
(``device/firmware/test_vectors.txt`` is shared by both test suites).

A frame on the wire is ``COBS(body + crc16_le(body)) + b"\\x00"`` where ``body`` starts with a
one-byte frame type. All integers are little-endian.
"""

from __future__ import annotations

import binascii
import re
import struct
from array import array
from dataclasses import dataclass
from functools import cache, lru_cache

import numpy as np

from tactile.device.protocol.info import (
    MAX_NAME,
    PROTOCOL_VERSION,
    ChannelSpec,
    DeviceInfo,
)
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
SUPPORTED_VERSIONS = frozenset({PROTOCOL_VERSION})  # header versions a receiver honours
# Smallest encoded frame, delimiter excluded: a samples frame of 1 x 1 (13-byte body, 2 CRC
# bytes, one COBS code byte).
MIN_ENCODED = _SAMPLES_HEAD.size + 2 + 2 + 1


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


# ---------------------------------------------------------------------------------------------
# Resynchronisation: the longest valid frame that ends a damaged chunk, in linear time


def find_frame(chunk: bytes, width: int | None = None) -> tuple[
        SamplesFrame | HeaderFrame | None, int, str]:
    """The frame in ``chunk`` (the bytes between two delimiters): ``(frame, skipped, failure)``.

    If the whole chunk is a frame, ``(frame, 0, "")``. Otherwise the longest suffix of it that is
    a valid frame is looked for (it recovers a frame that had garbage glued in front of it, or
    whose leading delimiter was lost): ``skipped`` is the number of bytes before it (all of them,
    ``len(chunk)``, when there is none) and ``failure`` says why the whole chunk was not a frame
    (``"crc"``: it has a frame's structure, but the CRC differs; ``"malformed"``: anything else).

    ``width``, when known, is the channel count a samples frame found in the search must have.
    The search costs O(len(chunk)) whatever the bytes (see :class:`_SuffixSearch`). A chunk
    holding a delimiter (0x00) is a caller's error: ValueError.
    """
    if 0 in chunk:
        raise ValueError("find_frame: the chunk holds a delimiter (0x00); split at them first")
    return _SuffixSearch(chunk, width).run()


# Where a suffix can start a frame. The chunk holds no zero byte, so the decoded byte at
# offset k of a candidate starting at i is chunk[i + 1 + k] when that byte is data, or 0 when it
# is the next code byte (a 0xFF block, the only exception, is longer than these offsets). A
# frame's type, channel and sample counts, header version and sample format are non-zero, so
# they must sit in the chunk at fixed places: the regular expression tests that in C.
_COUNT = rb"[\x01-\x20]"  # 1..32: WIRE_MAX_CHANNELS and MAX_SAMPLES_PER_FRAME


@cache
def _candidates(width: int | None) -> re.Pattern:
    channels = _COUNT if width is None else re.escape(bytes([width]))
    return re.compile(
        rb"(?=[\x02-\xff]\x02.{8}" + channels + _COUNT  # samples: code, type, seq, t, c, n
        + rb"|[\x02-\xff]\x01.{5}" + _COUNT + rb"\x01)",  # header: version, rate, c, format
        re.DOTALL,
    )


def _header_min(c):
    """Shortest decoded header (body and CRC) with ``c`` channels: one-byte names, no unit."""
    return _HEADER_HEAD.size + 1 + c * (2 + 1 + _CHANNEL_NUMS.size) + 2


def _header_max(c):
    """Longest decoded header with ``c`` channels: every string of MAX_NAME bytes."""
    return _HEADER_HEAD.size + 1 + MAX_NAME + c * (2 + 2 * MAX_NAME + _CHANNEL_NUMS.size) + 2


def _plausible(chunk: bytes, i: int, n: int) -> bool:
    """The length test of :meth:`_SuffixSearch._starts` for one regular-expression match."""
    d = n - i
    lo, hi = d - 2 - d // 254, d - 1
    if chunk[i + 1] == TYPE_SAMPLES:
        want = _SAMPLES_HEAD.size + 2 * chunk[i + 10] * chunk[i + 11] + 2
        return lo <= want <= hi
    c = chunk[i + 7]
    return _header_min(c) <= hi and _header_max(c) >= lo


@lru_cache(maxsize=1)
def _shift_table() -> array:
    """``x^(8k) * r mod G`` for every byte count ``k <= MAX_ENCODED`` as two 256-entry tables
    (low and high byte of ``r``) per ``k``: what ``crc_hqx(bytes(k), r)`` gives, in O(1)."""
    crc_table = np.array([binascii.crc_hqx(bytes([b]), 0) for b in range(256)], np.uint32)
    state = np.concatenate([np.arange(256), np.arange(256) << 8]).astype(np.uint32)
    out = np.empty((MAX_ENCODED + 1, 512), np.uint32)
    step = 64
    for k in range(step):  # one zero byte at a time...
        out[k] = state
        state = ((state << 8) & 0xFFFF) ^ crc_table[state >> 8]
    for k in range(step, len(out), step):  # ...then `step` bytes at a time, by the table
        prev = out[k - step : k]
        out[k : k + step] = (state[prev & 0xFF] ^ state[256 + (prev >> 8)])[: len(out) - k]
    return array("H", out.astype(np.uint16).tobytes())


class _SuffixSearch:
    """Every suffix of a chunk that could be a frame, checked in O(1) each after O(n) work.

    A COBS encoding is a chain of code bytes, each pointing at the next, that lands exactly on
    the chunk's end, so the chains of all candidate starts merge: their decoded lengths, their
    last two decoded bytes (the CRC) and the zero-initialised CRC-16 of their decoded bytes are
    computed once per code byte, right to left, and shared. CRC-16 is linear, so the CRC of a
    suffix follows from its block's CRC shifted past what comes after it (a table lookup), and
    the CRC check of a candidate needs no decoding. Only a candidate that passes it is decoded
    and parsed. Cheap tests first (type byte, frame length, channel and sample counts) keep
    the chains walked few; none of it depends on how many candidates there are.
    """

    def __init__(self, chunk: bytes, width: int | None) -> None:
        n = len(chunk)
        self.chunk, self.n, self.width = chunk, n, width
        self.dlen = [-2] * (n + 1)  # decoded length of chunk[p:]; -1 not a COBS chain
        self.crc = [0] * (n + 1)  # crc_hqx(decoded(chunk[p:]), 0)
        self.tail: list[bytes] = [b""] * (n + 1)  # last two decoded bytes
        self.dlen[n] = 0

    def run(self) -> tuple[SamplesFrame | HeaderFrame | None, int, str]:
        chunk, n = self.chunk, self.n
        failure = "malformed"
        if n < MIN_ENCODED:
            return None, n, failure
        if _candidates(None).match(chunk) and _plausible(chunk, 0, n):  # the whole chunk
            decoded = cobs_decode(chunk)
            if decoded is not None and len(decoded) >= 3:
                body = decoded[:-2]
                if crc16(body) == int.from_bytes(decoded[-2:], "little"):
                    parsed = parse_body(body)
                    if parsed is not None:
                        return parsed, 0, ""
                else:
                    failure = "crc"
        shift = _shift_table()
        for i in self._starts():
            if i == 0:
                continue
            length = self._walk(i)
            if chunk[i + 1] == TYPE_SAMPLES:
                if length != _SAMPLES_HEAD.size + 2 * chunk[i + 10] * chunk[i + 11] + 2:
                    continue
            elif length < 3:
                continue
            tail = self.tail[i]
            residue = shift[length * 512 + 0xFF] ^ shift[length * 512 + 256 + 0xFF] ^ self.crc[i]
            if residue != binascii.crc_hqx(tail, tail[0] | tail[1] << 8):
                continue
            decoded = cobs_decode(chunk[i:])
            parsed = parse_body(decoded[:-2]) if decoded is not None else None
            if parsed is None:
                continue
            if isinstance(parsed, SamplesFrame) and self.width is not None \
                    and parsed.raw.shape[1] != self.width:
                continue
            return parsed, i, failure
        return None, n, failure

    def _starts(self) -> list[int]:
        """Ascending offsets where a frame could start, by the bytes at fixed places and the
        length they imply (numpy on long chunks, the regular expression on short ones)."""
        chunk, n, width = self.chunk, self.n, self.width
        if n < 64:
            starts = []
            for m in _candidates(width).finditer(chunk):
                i = m.start()
                if n - i < MIN_ENCODED:
                    break
                if _plausible(chunk, i, n):
                    starts.append(i)
            return starts
        a = np.frombuffer(chunk, np.uint8).astype(np.int32)
        m = n - 11
        d = n - np.arange(m)
        lo, hi = d - 2 - d // 254, d - 1  # the decoded length lies in [lo, hi]
        code, kind = a[:m], a[1 : m + 1]
        c, k = a[10 : m + 10], a[11 : m + 11]
        chans = (c >= 1) & (c <= WIRE_MAX_CHANNELS) if width is None else c == width
        want = _SAMPLES_HEAD.size + 2 * c * k + 2
        samples = (code >= 2) & (kind == TYPE_SAMPLES) & chans & (k >= 1) \
            & (k <= MAX_SAMPLES_PER_FRAME) & (want >= lo) & (want <= hi)
        hc = a[7 : m + 7]
        header = (code >= 2) & (kind == TYPE_HEADER) \
            & (hc >= 1) & (hc <= WIRE_MAX_CHANNELS) & (a[8 : m + 8] == SAMPLE_FORMAT_INT16) \
            & (_header_min(hc) <= hi) & (_header_max(hc) >= lo)
        return np.flatnonzero(samples | header).tolist()

    def _walk(self, i: int) -> int:
        """Decoded length of ``chunk[i:]`` (-1 if not a COBS encoding), filling the shared
        tables along its chain; each code byte is visited once per chunk."""
        chunk, n, dlen, crc, tail = self.chunk, self.n, self.dlen, self.crc, self.tail
        stack = []
        p = i
        while dlen[p] == -2:
            q = p + chunk[p]
            if q > n:
                dlen[p] = -1
                break
            stack.append(p)
            p = q
        shift = _shift_table()
        for p in reversed(stack):
            q = p + chunk[p]
            dq = dlen[q]
            if dq < 0:
                dlen[p] = -1
                continue
            block = chunk[p + 1 : q]
            if chunk[p] != 0xFF and q != n:
                block += b"\x00"
            r = binascii.crc_hqx(block, 0)
            crc[p] = shift[dq * 512 + (r & 0xFF)] ^ shift[dq * 512 + 256 + (r >> 8)] ^ crc[q]
            dlen[p] = len(block) + dq
            tail[p] = tail[q] if dq >= 2 else (block + tail[q])[-2:]
        return dlen[i]
