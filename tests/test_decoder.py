"""Stream decoder: fuzzing, corruption recovery, gaps, duplicates, restarts, CSV mode."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import pen_stream
from hypothesis import given, settings
from hypothesis import strategies as st

from tactile.device.protocol import (
    MAX_ENCODED,
    ChannelSpec,
    DeviceInfo,
    Gap,
    Header,
    Samples,
    StreamDecoder,
    cobs_encode,
    decode,
    encode_header,
    encode_samples,
    pen_info,
)
from tactile.device.protocol.codec import samples_body
from tactile.errors import ConfigError


def feed_chunked(data: bytes, rng: np.random.Generator, dec: StreamDecoder | None = None):
    dec = dec or StreamDecoder()
    events = []
    i = 0
    while i < len(data):
        k = int(rng.integers(1, 300))
        events += dec.feed(data[i : i + k])
        i += k
    return events, dec


def delivered(events):
    """(seqs, raw rows) of all delivered samples, in delivery order."""
    seqs, rows = [], []
    for e in events:
        if isinstance(e, Samples):
            seqs.extend(range(e.seq, e.seq + len(e.raw)))
            rows.append(e.raw)
    return np.array(seqs, dtype=np.int64), (np.concatenate(rows) if rows else np.zeros((0, 8)))


def check_no_invention(events, raw):
    """Every delivered sample is the original sample of that seq, in strictly rising order."""
    seqs, rows = delivered(events)
    assert np.all(np.diff(seqs) > 0), "samples reordered or repeated"
    assert seqs.size == 0 or seqs.max() < len(raw)
    np.testing.assert_array_equal(rows, raw[seqs])
    # gaps account exactly for every jump in the sequence
    expected_next = None
    for e in events:
        if isinstance(e, Gap):
            assert e.reason == "drop" and e.missing > 0
            assert expected_next is not None and e.seq == expected_next + e.missing
            expected_next = e.seq
        elif isinstance(e, Samples):
            if expected_next is not None:
                assert e.seq == expected_next, "a jump in seq without a gap event"
            expected_next = e.seq + len(e.raw)
    return seqs


def test_clean_stream_any_chunking(rng):
    data, spans, raw = pen_stream(1000, per_frame=3)
    for _ in range(5):
        events, dec = feed_chunked(data, rng)
        seqs = check_no_invention(events, raw)
        assert seqs.tolist() == list(range(1000))
        assert dec.stats.errors == 0 and dec.stats.bytes_discarded == 0
        assert isinstance(events[0], Header) and events[0].info == pen_info()
        # per_frame=3: a header precedes samples 0, 300, 600, 900
        assert dec.stats.header_frames == 4 and dec.stats.header_changes == 0


def test_one_byte_at_a_time():
    data, _, raw = pen_stream(50)
    dec = StreamDecoder()
    events = [e for b in data for e in dec.feed(bytes([b]))]
    assert delivered(events)[0].tolist() == list(range(50))


def test_crc_failures_are_counted_and_become_gaps():
    info = pen_info()
    raw = np.arange(40 * 8, dtype=np.int16).reshape(40, 8)
    bad = {3, 4, 17, 39}
    out = bytearray(encode_header(info))
    for s in range(40):
        body = samples_body(s, s * 10_000, raw[s : s + 1])
        crc = 0x1234 if s in bad else None
        if crc is None:
            out += encode_samples(s, s * 10_000, raw[s : s + 1])
        else:
            out += cobs_encode(body + crc.to_bytes(2, "little")) + b"\x00"
    events, stats = decode(bytes(out))
    assert stats.crc_errors == 4 and stats.malformed == 0
    # 3-4 is one gap of 2; 17 one gap; 39 is the last frame: lost with nothing after it
    gaps = [(e.seq, e.missing) for e in events if isinstance(e, Gap)]
    assert gaps == [(5, 2), (18, 1)]
    assert stats.samples == 36 and stats.samples_lost == 3


def test_garbage_between_frames_is_discarded_and_counted(rng):
    data, spans, raw = pen_stream(300)
    out = bytearray()
    garbage_bytes = 0
    for start, end, _, _ in spans:
        if rng.random() < 0.3:
            g = bytes(rng.integers(1, 256, int(rng.integers(1, 40))).astype(np.uint8))
            out += g
            garbage_bytes += len(g)
        out += data[start:end]
    events, dec = feed_chunked(bytes(out), rng)
    seqs = check_no_invention(events, raw)
    assert seqs.tolist() == list(range(300)), "a frame after garbage was not recovered"
    assert dec.stats.bytes_discarded == garbage_bytes


def test_lost_delimiter_recovers_the_next_frame():
    data, spans, raw = pen_stream(20, header_every=0)
    out = bytearray(data)
    start, end, _, _ = spans[5]
    out[end - 1] = 0x07  # frame 5's delimiter becomes a data byte: 5 and 6 merge
    events, stats = decode(bytes(out))
    assert delivered(events)[0].tolist() == [s for s in range(20) if s != 5]
    assert stats.malformed + stats.crc_errors == 1


def test_duplicated_frames_are_dropped():
    data, spans, raw = pen_stream(60, header_every=0)
    out = bytearray()
    for k, (start, end, _, _) in enumerate(spans):
        out += data[start:end]
        if k % 7 == 0:
            out += data[start:end]
    events, stats = decode(bytes(out))
    assert delivered(events)[0].tolist() == list(range(60))
    assert stats.duplicates == 9 and stats.gaps == 0


def test_partly_overlapping_resend_keeps_only_new_samples():
    raw = np.arange(10 * 8, dtype=np.int16).reshape(10, 8)
    data = encode_samples(0, 0, raw[0:4]) + encode_samples(2, 20_000, raw[2:7])
    events, stats = decode(data)
    seqs, rows = delivered(events)
    assert seqs.tolist() == list(range(7))
    np.testing.assert_array_equal(rows, raw[:7])


def test_sequence_wraps_without_a_gap():
    raw = np.zeros((1, 8), np.int16)
    data = b"".join(encode_samples((2**32 - 3 + i) % 2**32, i, raw) for i in range(6))
    events, stats = decode(data)
    assert delivered(events)[0].tolist() == list(range(2**32 - 3, 2**32 + 3))
    assert stats.gaps == 0


def test_restart_is_a_gap_and_host_seq_stays_monotonic():
    raw = np.zeros((1, 8), np.int16)
    before = b"".join(encode_samples(5000 + i, i, raw) for i in range(5))
    after = encode_header(pen_info()) + b"".join(encode_samples(i, i, raw) for i in range(5))
    events, stats = decode(before + after)
    assert delivered(events)[0].tolist() == list(range(5000, 5010))
    assert [e for e in events if isinstance(e, Gap)] == [Gap(5005, 0, "restart")]
    assert stats.restarts == 1


def test_header_change_is_reported_and_mismatched_frames_dropped():
    from tactile.device.protocol import PEN_CHANNELS, DeviceInfo

    other = DeviceInfo(100.0, PEN_CHANNELS[2:5], "imu-only")
    data = (
        encode_header(pen_info())
        + encode_samples(0, 0, np.zeros((1, 8), np.int16))
        + encode_header(other)
        + encode_samples(1, 10, np.zeros((1, 8), np.int16))  # contradicts the new header
        + encode_samples(2, 20, np.zeros((1, 3), np.int16))
    )
    events, stats = decode(data)
    headers = [e for e in events if isinstance(e, Header)]
    assert [h.changed for h in headers] == [False, True] and headers[1].info == other
    assert stats.header_changes == 1 and stats.malformed == 1


def test_buffer_stays_bounded_on_endless_garbage(rng):
    dec = StreamDecoder(mode="binary")
    for _ in range(200):
        dec.feed(bytes(rng.integers(1, 256, 1000).astype(np.uint8)))
        assert len(dec._buf) <= MAX_ENCODED
    auto = StreamDecoder()
    for _ in range(50):
        auto.feed(bytes(rng.integers(1, 256, 1000).astype(np.uint8)))
        assert len(auto._buf) <= 8192


@st.composite
def corrupted_streams(draw):
    n = draw(st.integers(1, 120))
    per_frame = draw(st.sampled_from([1, 1, 2, 5]))
    data, spans, raw = pen_stream(n, per_frame, seed=draw(st.integers(0, 1000)))
    data = bytearray(data)
    ops = draw(
        st.lists(
            st.tuples(
                st.sampled_from(["flip", "insert", "delete", "dup", "drop"]),
                st.integers(0, len(data) - 1),
                st.binary(min_size=1, max_size=30),
            ),
            max_size=12,
        )
    )
    damaged = np.zeros(len(data) + 1, bool)  # original bytes flipped or deleted
    inserted = np.zeros(len(data) + 1, bool)  # bytes inserted just before this position
    # apply from the end backwards so that earlier positions stay valid
    pieces = {i: bytes([b]) for i, b in enumerate(data)}
    extra_before = {}
    for op, pos, blob in sorted(ops, key=lambda o: -o[1]):
        if op == "flip":
            pieces[pos] = bytes([pieces[pos][0] ^ (1 << (blob[0] % 8))]) if pieces[pos] else b""
            damaged[pos] = True
        elif op == "insert":
            extra_before[pos] = extra_before.get(pos, b"") + blob
            inserted[pos] = True
        elif op == "delete":
            for i in range(pos, min(pos + len(blob), len(data))):
                pieces[i] = b""
                damaged[i] = True
        else:
            span = next(s for s in spans if s[0] <= pos < s[1])
            if op == "dup":
                extra_before[span[1]] = extra_before.get(span[1], b"") + bytes(
                    data[span[0] : span[1]]
                )
            else:
                for i in range(span[0], span[1]):
                    pieces[i] = b""
                    damaged[i] = True
    out = b"".join(extra_before.get(i, b"") + pieces[i] for i in range(len(data)))
    out += extra_before.get(len(data), b"")
    return out, spans, raw, damaged, inserted


@given(case=corrupted_streams(), seed=st.integers(0, 2**32 - 1))
@settings(max_examples=300, deadline=None)
def test_fuzz_corruptions(case, seed):
    out, spans, raw, damaged, inserted = case
    events, dec = feed_chunked(out, np.random.default_rng(seed))
    seqs = check_no_invention(events, raw)
    got = set(seqs.tolist())
    for start, end, first, n in spans:
        # an insertion recorded at `start` lands before the frame, outside it
        inner = damaged[start:end].any() or inserted[start + 1 : end].any()
        if n and not inner:
            assert set(range(first, first + n)) <= got, "an intact frame was lost"
    assert dec.stats.samples == len(seqs)


@given(st.binary(max_size=3000), st.sampled_from(["auto", "binary", "csv"]))
@settings(max_examples=300, deadline=None)
def test_random_bytes_never_raise_or_invent(data, mode):
    dec = StreamDecoder(mode=mode)
    events = dec.feed(data)
    for e in events:  # random bytes can only look like CSV rows, never like CRC-checked frames
        assert not (isinstance(e, Samples) and e.raw.dtype == np.int16)


# -- CSV mode ------------------------------------------------------------------------------------


def test_csv_auto_detected_with_names_and_rejections():
    text = (
        b"boot: ok!\r\nax,ay,az\r\n1,2,3\r\n4,5,6\r\n7,x,9\r\n1,2\r\nnan,1,2\r\n# c\r\n\r\n"
        b"1e39,0,0\r\n8 ,9, 10\r\n"  # 1e39 is finite, but inf as the model's float32
    )
    events, stats = decode(text)
    assert StreamDecoder().mode == "auto"
    header = next(e for e in events if isinstance(e, Header))
    assert header.info.channel_names == ("ax", "ay", "az")
    seqs, rows = delivered(events)
    assert seqs.tolist() == [0, 1, 6]
    np.testing.assert_array_equal(rows, [[1, 2, 3], [4, 5, 6], [8, 9, 10]])
    assert [e for e in events if isinstance(e, Gap)] == [Gap(6, 4, "rejected")]
    assert stats.csv_rows == 3 and stats.csv_rejected == 5  # boot: ok!, 7,x,9, 1,2, nan, 1e39


def test_csv_names_again_mid_run_are_no_lost_sample():
    """A board that restarts (a reconnection) or repeats its names line: the run's own names
    again were a rejected row, reported as one lost sample. Other names mid-run still are."""
    text = b"ax,ay,az\n1,2,3\n4,5,6\n7,8,9\nax,ay,az\n1,1,1\nbx,by,bz\n2,2,2\n"
    events, stats = decode(text)
    seqs, rows = delivered(events)
    assert seqs.tolist() == [0, 1, 2, 3, 5]  # bx,by,bz: rejected, the row after it one later
    np.testing.assert_array_equal(rows, [[1, 2, 3], [4, 5, 6], [7, 8, 9], [1, 1, 1], [2, 2, 2]])
    assert [e for e in events if isinstance(e, Gap)] == [Gap(5, 1, "rejected")]
    assert stats.csv_rejected == 1 and stats.bytes_discarded == len(b"bx,by,bz\n")
    assert sum(isinstance(e, Header) for e in events) == 1


def test_csv_rows_after_a_reconnection_follow_a_restart_gap():
    """A CSV board's lines carry no count: after the link was re-opened (a board that was
    unplugged and restarted, printing its names again), its rows joined the earlier ones as one
    run. The first row after it now follows a restart gap, as a binary pen's frame does."""
    dec = StreamDecoder()
    events = dec.feed(b"ax,ay\n1,2\n3,4\n5,6\n")
    dec.reconnected()
    events += dec.feed(b"ax,ay\n7,8\n9,10\n")
    seqs, rows = delivered(events)
    assert seqs.tolist() == [0, 1, 2, 3, 4]
    assert [e for e in events if isinstance(e, Gap)] == [Gap(3, 0, "restart")]
    assert (dec.stats.restarts, dec.stats.gaps, dec.stats.csv_rejected) == (1, 1, 0)


def test_csv_without_names_and_blank_separated():
    events, stats = decode(b"1 2\n3 4\n5 6\n", csv_rate_hz=50.0)
    header = next(e for e in events if isinstance(e, Header))
    assert header.info.channel_names == ("ch0", "ch1") and header.info.sample_rate_hz == 50.0
    samples = [e for e in events if isinstance(e, Samples)]
    assert [s.t_us for s in samples] == [0, 20_000, 40_000]


def test_csv_split_anywhere_gives_the_same_result(rng):
    text = b"".join(b"%d,%d,%d\n" % (i, -i, 2 * i) for i in range(200))
    ref, _ = decode(text)
    events, _ = feed_chunked(text, rng, StreamDecoder(line_start=True))
    assert delivered(events)[0].tolist() == delivered(ref)[0].tolist() == list(range(200))


def test_bad_decoder_settings():
    with pytest.raises(ConfigError, match="mode 'hex'"):
        StreamDecoder(mode="hex")
    with pytest.raises(ConfigError, match="csv rate"):
        StreamDecoder(csv_rate_hz=0)


# -- issue 21: the decoder under hostile input ---------------------------------------------------


def test_csv_lines_too_wide_or_names_too_long_never_raise():
    d = StreamDecoder()
    row = b",".join([b"1"] * 33) + b"\n"  # 33 channels: a CSV device may have them
    assert d.feed(row) == [] and d.feed(row) == []
    wide = b",".join([b"1"] * 2049) + b"\n"  # more fields than a line may hold
    assert d.feed(wide) == [] and d.feed(wide) == []
    long_name = b"x" * 33 + b",b,c\n"
    events = d.feed(b"\n" + long_name + b"1,2,3\n4,5,6\n7,8,9\n" + row + b"10,11,12\n")
    events += d.finish()  # (rows of a stream opened mid-run wait for a names line)
    seqs, rows = delivered(events)
    assert seqs.tolist() == [0, 1, 2, 4]  # the 33-field row is one rejected sample
    np.testing.assert_array_equal(rows, [[1, 2, 3], [4, 5, 6], [7, 8, 9], [10, 11, 12]])
    assert d.stats.csv_rejected >= 3 and [e for e in events if isinstance(e, Gap)] == [
        Gap(4, 1, "rejected")]


class _Counted:
    """Bytes handed to the COBS decoder and to the CRC, wherever the decoder calls them."""

    def __init__(self, monkeypatch):
        import binascii

        from tactile.device.protocol import codec as protocol
        from tactile.device.protocol import decoder

        self.decoded = self.crc_calls = 0
        real_decode, real_crc = protocol.cobs_decode, binascii.crc_hqx

        def decode(data):
            self.decoded += len(data)
            return real_decode(data)

        def crc(data, value):
            self.crc_calls += 1
            return real_crc(data, value)

        monkeypatch.setattr(protocol, "cobs_decode", decode)
        monkeypatch.setattr(decoder, "cobs_decode", decode, raising=False)
        monkeypatch.setattr(binascii, "crc_hqx", crc)


@pytest.mark.parametrize("mode, data, read", [
    ("binary", b"\x01" * 2573 + b"\x00", 4096),  # every suffix is valid COBS
    ("binary", (b"\x02" * 2573 + b"\x00") * 4, 4096),
    ("auto", b"\x01" * 2573 + b"\x00", 4096),
    ("auto", bytes(np.random.default_rng(0).integers(1, 256, 6000).astype(np.uint8)), 64),
    ("auto", (bytes(np.random.default_rng(1).integers(1, 256, 200).astype(np.uint8)) + b"\x00")
     * 40, 64),
])
def test_work_per_byte_is_bounded(monkeypatch, mode, data, read):
    """Resynchronisation and mode detection are linear: the bytes decoded and the CRCs taken
    stay within a small multiple of the input (not one decode per byte per candidate, nor one
    re-parse of everything held per read). Timing is measured by bench/fuzz.py, not here."""
    count = _Counted(monkeypatch)
    dec = StreamDecoder(mode)
    for i in range(0, len(data), read):
        dec.feed(data[i : i + read])
    assert count.decoded <= 2 * len(data), count.decoded
    assert count.crc_calls <= len(data), count.crc_calls


def test_csv_opened_mid_line_takes_its_width_from_agreeing_lines():
    dec = StreamDecoder()
    events = dec.feed(b"12,13\n1,2,3\n4,5,6\n7,8,9\n") + dec.finish()
    header = next(e for e in events if isinstance(e, Header))
    assert header.info.channel_names == ("ch0", "ch1", "ch2")
    seqs, rows = delivered(events)
    assert seqs.tolist() == [0, 1, 2]
    np.testing.assert_array_equal(rows, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    # cut within the first number: that line is not taken (its value would be wrong)
    dec = StreamDecoder()
    events = dec.feed(b"5.25,3,4\n15.5,1,2\n16,1,2\n17,1,2\n") + dec.finish()
    assert delivered(events)[1][:, 0].tolist() == [15.5, 16, 17]


def _rows(first: int, n: int) -> bytes:
    return b"".join(b"%d,%d,%d\n" % (i, -i, 2 * i) for i in range(first, first + n))


def test_csv_opened_mid_run_takes_the_names_a_board_repeats():
    """A port opened on a running board that repeats its names line got ch0..chN, and each
    names line after that was a rejected row (a lost sample, a gap that cut the windows):
    the rows now wait for a names line of their width, which names them all, and the later
    repeats are skipped."""
    dec = StreamDecoder()
    events = dec.feed(b"7,-7,14\n" + _rows(8, 92))  # opened within row 7: it is not taken
    assert events == []  # held: the board's names line may follow
    events = dec.feed(b"a,b,c\n" + _rows(100, 100) + b"a,b,c\n" + _rows(200, 5))
    assert [e for e in events if isinstance(e, Header)] == [Header(DeviceInfo(
        100.0, tuple(ChannelSpec(n, "") for n in "abc"), "csv"))]
    seqs, rows = delivered(events)
    assert seqs.tolist() == list(range(197)) and rows[:, 0].tolist() == list(range(8, 205))
    assert not [e for e in events if isinstance(e, Gap)] and dec.stats.gaps == 0
    assert dec.stats.csv_rejected == 1 and dec.stats.samples == 197  # the cut first line


def test_csv_opened_mid_run_without_names_goes_on_unnamed_after_two_seconds_of_rows():
    """Rows with no names line wait 2 s of rows at the CSV rate (100 Hz: 200 lines), then go
    on as ch0..; a stream that ends before gives its rows from finish(); a reconnection among
    the held rows is a restart gap in its place."""
    dec = StreamDecoder()
    assert dec.feed(b"0,0,0\n" + _rows(1, 198)) == []
    events = dec.feed(_rows(199, 3))
    assert next(e for e in events if isinstance(e, Header)).info.channel_names == (
        "ch0", "ch1", "ch2")
    assert delivered(events)[1][:, 0].tolist() == list(range(1, 202))
    assert dec.feed(b"a,b,c\n") == [] and dec.stats.csv_rejected == 2  # too late: rejected
    wide = (",".join(["1"] * 2000) + "\n").encode()  # 4 kB rows: held up to 256 KiB, not 2 s
    dec = StreamDecoder()
    assert dec.feed(b"x\n" + wide * 60) == []  # 240 kB: still held
    events = dec.feed(wide * 10)  # past 256 KiB: released (a 200-line wait would still hold)
    assert len(delivered(events)[0]) == 70

    dec = StreamDecoder(csv_rate_hz=20.0)  # 2 s are 40 rows; at least 64 are waited for
    assert dec.feed(b"0,0,0\n" + _rows(1, 30)) == []
    dec.reconnected()
    assert dec.feed(b"1,62\n" + _rows(32, 10)) == []  # the line the link re-opened within
    events = dec.finish()
    seqs, rows = delivered(events)
    assert rows[:, 0].tolist() == [*range(1, 31), *range(32, 42)]
    # as a named stream has them: the break, then the cut line as one rejected row
    assert [e for e in events if isinstance(e, Gap)] == [Gap(30, 0, "restart"),
                                                         Gap(31, 1, "rejected")]
    assert dec.finish() == []


def test_csv_width_from_a_run_of_rows_not_from_a_stray_line():
    text = b"a,b\n1,2,3\n9,9\n4,5,6\n7,8,9\n10,11,12\n"  # widths 2 (names), 3, 2, 3, 3, 3
    events, stats = decode(text)
    header = next(e for e in events if isinstance(e, Header))
    assert len(header.info.channels) == 3 and header.info.channel_names[0] == "ch0"
    seqs, rows = delivered(events)
    assert rows[:, 0].tolist() == [1, 4, 7, 10]
    assert seqs.tolist() == [0, 2, 3, 4]  # "9,9" after the first row is a lost sample


@pytest.mark.parametrize("field, ok", [
    ("10", True), ("-1.5", True), ("+.5", True), ("7.", True), ("1e3", True), ("-2.5E-3", True),
    ("1_0", False), ("0x10", False), ("inf", False), ("nan", False), ("1e", False),
    ("\u0661", False), ("\uff11", False), ("1.2.3", False), ("--1", False), ("0b1", False),
])
def test_csv_numbers_are_plain_decimals(field, ok):
    row = f"1,{field}\n".encode()
    events, stats = decode(b"1,1\n" + row + b"2,2\n3,3\n")
    rows = delivered(events)[1]
    assert len(rows) == (4 if ok else 3)
    if ok:
        assert rows[1, 1] == float(field)


def _frames(seq0, t0, raw, per=1, period=10_000):
    return b"".join(encode_samples(seq0 + s, t0 + s * period, raw[s : s + per])
                    for s in range(0, len(raw), per))


def test_unknown_protocol_version_is_refused_and_reported():
    from tactile.device.protocol import DeviceInfo

    v99 = DeviceInfo(100.0, pen_info().channels, "future-pen", 99)
    raw = np.arange(30 * 8, dtype=np.int16).reshape(30, 8)
    data = (encode_header(pen_info()) + _frames(0, 0, raw[:10])
            + encode_header(v99) + _frames(10, 100_000, raw[10:20])
            + encode_header(pen_info()) + _frames(20, 200_000, raw[20:]))
    for mode in ("auto", "binary"):
        events, stats = decode(data, mode)
        gaps = [e for e in events if isinstance(e, Gap)]
        assert [(g.seq, g.missing, g.reason) for g in gaps] == [
            (10, 0, "unsupported"), (20, 10, "drop")]
        assert "99" in gaps[0].detail
        seqs, rows = delivered(events)
        assert seqs.tolist() == list(range(10)) + list(range(20, 30))
        np.testing.assert_array_equal(rows, raw[seqs])
        assert stats.unsupported == 1 and stats.refused == 10
        assert [e.info.protocol_version for e in events if isinstance(e, Header)] == [1]
    # a device that only ever speaks version 99: nothing delivered, the event says why
    events, stats = decode(encode_header(v99) + _frames(0, 0, raw))
    assert not [e for e in events if isinstance(e, Samples)]
    assert [e.reason for e in events if isinstance(e, Gap)] == ["unsupported"]


def test_a_reboot_before_256_samples_is_a_restart():
    rng = np.random.default_rng(3)
    first = rng.integers(-2000, 2000, (100, 8)).astype(np.int16)
    second = rng.integers(-2000, 2000, (50, 8)).astype(np.int16)
    # the link stays open; the pen reboots at sample 100: header, then 0, 1, ... again, its
    # clock near zero again
    data = (encode_header(pen_info()) + _frames(0, 1200, first)
            + encode_header(pen_info()) + _frames(0, 1150, second))
    events, stats = decode(data)
    seqs, rows = delivered(events)
    assert seqs.tolist() == list(range(150))
    np.testing.assert_array_equal(rows, np.concatenate([first, second]))
    assert [e for e in events if isinstance(e, Gap)] == [Gap(100, 0, "restart")]
    assert stats.restarts == 1 and stats.duplicates == 0
    # and with the reboot's header lost, its contents still tell
    no_header = encode_header(pen_info()) + _frames(0, 1200, first) + _frames(0, 1150, second)
    events, _ = decode(no_header)
    assert [e for e in events if isinstance(e, Gap)] == [Gap(100, 0, "restart")]


def test_a_frame_resent_late_is_dropped_without_a_gap():
    raw = np.random.default_rng(4).integers(-2000, 2000, (400, 8)).astype(np.int16)
    frames = [encode_samples(s, s * 10_000, raw[s : s + 1]) for s in range(400)]
    frames.insert(300, frames[1])  # frame 1 re-sent 299 samples late
    events, stats = decode(encode_header(pen_info()) + b"".join(frames))
    seqs, rows = delivered(events)
    assert seqs.tolist() == list(range(400))
    np.testing.assert_array_equal(rows, raw)
    assert not [e for e in events if isinstance(e, Gap)]
    assert stats.duplicates == 1 and stats.restarts == 0


def test_before_a_header_a_kept_tail_moves_on_in_time_and_one_width_is_delivered():
    raw = np.arange(10 * 8, dtype=np.int16).reshape(10, 8)
    # no header: 0-3 at 10 ms per sample, then 2-6 re-sent: its new tail 4-6 is 40 ms on
    data = encode_samples(0, 0, raw[0:4]) + encode_samples(2, 20_000, raw[2:7])
    data += encode_samples(7, 70_000, np.zeros((1, 3), np.int16))  # another width: dropped
    data += encode_samples(7, 70_000, raw[7:8])
    events, stats = decode(data)
    samples = [e for e in events if isinstance(e, Samples)]
    assert [(s.seq, s.t_us) for s in samples] == [(0, 0), (4, 40_000), (7, 70_000)]
    assert {s.raw.shape[1] for s in samples} == {8} and stats.malformed == 1


def test_a_frame_behind_its_whole_run_after_a_header_is_read_as_a_restart():
    """device/PROTOCOL.md, "Restart": the bytes of fuzz seed 1 case 280077 and seed 5 case 4667
    (minimised), a device's frames with counts 1 and 0 swapped, a header between them, are the
    bytes of a device that restarted again before its first frame got through. The reading
    that loses nothing and never joins two runs of a device: a restart, whatever the clocks."""
    from tactile.device.protocol import ChannelSpec, DeviceInfo

    raw = np.random.default_rng(5).integers(-2000, 2000, (4, 8)).astype(np.int16)
    other = DeviceInfo(100.0, tuple(ChannelSpec(f"x{i}", "u") for i in range(8)), "pen")
    one, zero = encode_samples(1, 27_582, raw[1:2]), encode_samples(0, 17_582, raw[0:1])
    two = encode_samples(2, 37_582, raw[2:3])

    def seen(events):  # samples as (seq, t_us, first row), gaps as they are
        return [(e.seq, e.t_us, e.raw[0].tolist()) if isinstance(e, Samples) else e
                for e in events if isinstance(e, Samples | Gap)]

    def s(seq, t_us, k):
        return (seq, t_us, raw[k].tolist())

    for head in (encode_header(pen_info()), encode_header(other)):
        events, stats = decode(one + head + zero + two)
        assert seen(events) == [
            s(1, 27_582, 1), Gap(2, 0, "restart"), s(2, 37_582, 0), Gap(4, 1, "drop"),
            s(4, 57_582, 2)]
        assert stats.restarts == 1 and stats.late == 0
    # without a header between them, count 0 is a late frame: dropped, no gap
    events, stats = decode(one + zero + two)
    assert seen(events) == [s(1, 27_582, 1), s(2, 37_582, 2)]
    assert stats.late == 1 and stats.restarts == 0
    # nor after a header when no device that started recently counts there (4,096 and up)
    late = encode_samples(5001, 27_582, raw[1:2]) + encode_header(other) \
        + encode_samples(5000, 17_582, raw[0:1])
    events, stats = decode(late)
    assert seen(events) == [s(5001, 27_582, 1)]
    assert stats.late == 1
