"""Frame codec: COBS, CRC, encoder/parser round trips and the shared vectors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tactile.device.protocol import (
    MAX_ENCODED,
    ChannelSpec,
    DeviceInfo,
    HeaderFrame,
    SamplesFrame,
    cobs_decode,
    cobs_encode,
    crc16,
    encode_header,
    encode_samples,
    f32,
    parse_frame,
    pen_info,
    vectors,
)
from tactile.errors import FrameError


def test_crc_catalogue_check_value():
    # independent reference: the CRC catalogue's check value for CRC-16/CCITT-FALSE
    assert crc16(b"123456789") == 0x29B1


@pytest.mark.parametrize(
    "data, encoded",
    [  # the published COBS examples
        (b"", b"\x01"),
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
        (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255))),
        (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
        (bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
    ],
)
def test_cobs_published_examples(data, encoded):
    assert cobs_encode(data) == encoded
    assert cobs_decode(encoded) == data


@given(st.binary(max_size=1200))
@settings(max_examples=300, deadline=None)
def test_cobs_round_trip(data):
    enc = cobs_encode(data)
    assert 0 not in enc
    assert len(enc) <= len(data) + len(data) // 254 + 1
    assert cobs_decode(enc) == data


@given(
    seq=st.integers(0, 2**32 - 1),
    t_us=st.integers(0, 2**32 - 1),
    n=st.integers(1, 32),
    c=st.integers(1, 32),
    seed=st.integers(0, 2**32 - 1),
)
@settings(max_examples=200, deadline=None)
def test_samples_round_trip(seq, t_us, n, c, seed):
    raw = np.random.default_rng(seed).integers(-32768, 32768, (n, c)).astype(np.int16)
    wire = encode_samples(seq, t_us, raw)
    assert wire[-1] == 0 and 0 not in wire[:-1]
    assert len(wire) - 1 <= MAX_ENCODED
    parsed = parse_frame(wire[:-1])
    assert isinstance(parsed, SamplesFrame)
    assert (parsed.seq, parsed.t_us) == (seq, t_us)
    assert parsed.raw.dtype == np.int16 and parsed.raw.shape == (n, c)
    np.testing.assert_array_equal(parsed.raw, raw)


_text = st.text(
    alphabet=st.characters(min_codepoint=32, max_codepoint=0x2FF), min_size=1, max_size=10
)


@given(
    rate=st.floats(0.5, 1e5),
    names=st.lists(_text, min_size=1, max_size=32, unique=True),
    unit=st.text(max_size=8),
    scale=st.floats(1e-6, 1e3),
    offset=st.floats(-1e3, 1e3),
)
@settings(max_examples=100, deadline=None)
def test_header_round_trip(rate, names, unit, scale, offset):
    chans = tuple(ChannelSpec(n, unit, f32(scale), f32(offset)) for n in names)
    info = DeviceInfo(f32(rate), chans, device="dev")
    parsed = parse_frame(encode_header(info)[:-1])
    assert isinstance(parsed, HeaderFrame)
    assert parsed.info == info


def test_pen_header_is_float32_exact():
    # the header carries float32; the pen's own constants must survive the trip unchanged
    assert parse_frame(encode_header(pen_info())[:-1]).info == pen_info()


def test_every_single_bit_flip_is_caught():
    wire = encode_samples(42, 420_000, np.arange(8, dtype=np.int16).reshape(1, 8))[:-1]
    for i in range(len(wire)):
        for b in range(8):
            bad = bytearray(wire)
            bad[i] ^= 1 << b
            assert parse_frame(bytes(bad)) is None, (i, b)


@pytest.mark.parametrize(
    "args, match",
    [
        ((0, 0, np.zeros((0, 8))), "samples x"),
        ((0, 0, np.zeros((33, 8))), "samples x"),
        ((0, 0, np.zeros((1, 33))), "samples x"),
        ((0, 0, np.zeros(8)), "2-D"),
        ((0, 0, np.full((1, 8), 40000)), "int16 range"),
    ],
)
def test_encoder_rejects_bad_input(args, match):
    with pytest.raises(FrameError, match=match):
        encode_samples(*args)


def test_device_info_validation():
    with pytest.raises(FrameError, match="duplicate"):
        DeviceInfo(100.0, (ChannelSpec("a", "g"), ChannelSpec("a", "g")))
    with pytest.raises(FrameError, match="sample rate"):
        DeviceInfo(float("nan"), (ChannelSpec("a", "g"),))
    with pytest.raises(FrameError, match="scale"):
        ChannelSpec("a", "g", 0.0)
    with pytest.raises(FrameError, match="overflow float32"):
        ChannelSpec("a", "g", 1e35)  # 32767 counts would be inf in the model's float32 input
    ChannelSpec("a", "g", 1e33)  # 3.3e37 at full scale: representable
    with pytest.raises(FrameError, match="channels"):
        DeviceInfo(100.0, ())


def test_python_encoder_matches_shared_vectors():
    cases = vectors.load()
    kinds = {k for k, _ in cases}
    assert kinds == {"crc", "cobs", "samples", "header"}
    for kind, f in cases:
        if kind == "crc":
            data = b"" if f["data"] == "-" else bytes.fromhex(f["data"])
            assert crc16(data) == int(f["crc"], 16)
        elif kind == "cobs":
            data = b"" if f["data"] == "-" else bytes.fromhex(f["data"])
            assert cobs_encode(data).hex() == f["encoded"]
        elif kind == "samples":
            assert encode_samples(*vectors.samples_args(f)).hex() == f["frame"]
        else:
            assert encode_header(vectors.header_info(f)).hex() == f["frame"]
    # and the file is what the generator makes now (a protocol change must regenerate it)
    assert [line for line in vectors.generate() if not line.startswith("#")] == [
        line for line in vectors.VECTORS.read_text().splitlines() if not line.startswith("#")
    ]


def test_find_frame_refuses_a_chunk_holding_a_delimiter():
    # the suffix search assumes zero-free chunks; with a 0x00 inside it never ended
    from tactile.device.protocol import find_frame

    with pytest.raises(ValueError, match="delimiter"):
        find_frame(b"\x03\x02\x00\x01")
