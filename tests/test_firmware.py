"""The firmware's C frame encoder: shared vectors, refusals, and random frames the host decodes.

The encoder (``device/firmware/tactile_pen/src/tactile_frame.c``, the one copy the sketch
builds) is compiled with the system C compiler (``$CC`` or ``cc``) together with the host test
program ``device/firmware/test_vectors_main.c``: with AddressSanitizer and UBSan when this
machine can build and run them, else without (``test_sanitizer_build`` skips and says so).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from tactile.device.protocol import (
    MAX_ENCODED,
    SUPPORTED_VERSIONS,
    Gap,
    Header,
    Samples,
    cobs_encode,
    crc16,
    decode,
    encode_header,
    encode_samples,
    f32,
    pen_info,
    vectors,
)
from tactile.device.protocol.codec import MAX_BODY

REPO = Path(__file__).resolve().parents[1]
FIRMWARE = REPO / "device" / "firmware"
SRC = FIRMWARE / "tactile_pen" / "src"
SOURCES = (SRC / "tactile_frame.c", FIRMWARE / "test_vectors_main.c")
WARNINGS = ("-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror")
SANITIZE = (
    "-fsanitize=address,undefined",
    "-fno-sanitize-recover=all",
    "-fno-omit-frame-pointer",
    "-g",
)
# the harness's own allocations are not the encoder's business; the encoder never allocates
RUN_ENV = {"ASAN_OPTIONS": "detect_leaks=0", "UBSAN_OPTIONS": "print_stacktrace=1"}
SUMMARY = re.compile(r"^(\d+) passed, (\d+) failed$")


@dataclass(frozen=True)
class Program:
    exe: Path
    sanitized: bool
    note: str  # why the sanitizers are off, if they are

    def run(self, *args: str, stdin: bytes = b"") -> subprocess.CompletedProcess:
        env = {**os.environ, **RUN_ENV}
        return subprocess.run(
            [str(self.exe), *args], input=stdin, capture_output=True, timeout=60, env=env
        )


def _compiler() -> list[str] | None:
    cc = shlex.split(os.environ.get("CC", "")) or ["cc"]
    return cc if shutil.which(cc[0]) else None


def _build(cc: list[str], exe: Path, extra: tuple[str, ...]) -> subprocess.CompletedProcess:
    cmd = [*cc, *WARNINGS, "-O2", *extra, f"-I{SRC}", *map(str, SOURCES), "-o", str(exe)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def program(tmp_path_factory: pytest.TempPathFactory) -> Program:
    cc = _compiler()
    if cc is None:
        msg = f"no C compiler ({os.environ.get('CC') or 'cc'}; set $CC): C encoder not tested"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    out = tmp_path_factory.mktemp("firmware")
    exe = out / "test_vectors_san"
    built = _build(cc, exe, SANITIZE)
    if built.returncode == 0:
        prog = Program(exe, True, "")
        probe = prog.run("--info")
        if probe.returncode == 0:
            return prog
        note = f"sanitized build does not run here: {probe.stderr.decode()[-300:].strip()}"
    else:
        note = f"sanitizers unavailable: {built.stderr[-300:].strip()}"
    exe = out / "test_vectors"
    built = _build(cc, exe, ())
    # warnings are errors: firmware code that does not compile cleanly fails the suite
    assert built.returncode == 0, built.stderr
    return Program(exe, False, note)


def _summary(stdout: bytes) -> tuple[int, int]:
    lines = stdout.decode().splitlines()
    assert lines, "no output"
    m = SUMMARY.match(lines[-1])
    assert m, f"last line is not 'N passed, N failed': {lines[-1]!r}"
    return int(m[1]), int(m[2])


def test_c_encoder_passes_every_vector(program: Program):
    cases = vectors.load()
    res = program.run(str(vectors.VECTORS))
    passed, failed = _summary(res.stdout)
    assert res.returncode == 0 and failed == 0, res.stdout.decode() + res.stderr.decode()
    assert passed == len(cases)  # every line of the file ran: nothing skipped


def test_c_vector_runner_reports_failures(program: Program, tmp_path: Path):
    # the runner itself must not pass what it should not: a wrong byte, an unknown kind,
    # an unknown key, a missing key
    lines = vectors.VECTORS.read_text().splitlines()
    first = next(i for i, s in enumerate(lines) if s.startswith("samples "))
    good = lines[first]
    last = good[-4:]
    lines[first] = good[:-4] + ("00" if last[:2] != "00" else "11") + last[2:]
    lines += ["crcx data=00 crc=e1f0", "crc data=00 crc=e1f0 extra=1", "cobs data=00"]
    bad = tmp_path / "bad_vectors.txt"
    bad.write_text("\n".join(lines) + "\n")
    res = program.run(str(bad))
    passed, failed = _summary(res.stdout)
    assert res.returncode != 0
    assert failed == 4 and passed == len(vectors.load()) - 1
    out = res.stdout.decode()
    n = len(lines)
    for lineno in (first + 1, n - 2, n - 1, n):
        assert f"line {lineno}: " in out


def test_python_encoder_reproduces_every_vector():
    cases = vectors.load()
    assert {kind for kind, _ in cases} == {"crc", "cobs", "samples", "header"}
    for kind, f in cases:
        if kind in ("crc", "cobs"):
            data = bytes.fromhex("" if f["data"] == "-" else f["data"])
        if kind == "crc":
            assert f"{crc16(data):04x}" == f["crc"]
        elif kind == "cobs":
            assert cobs_encode(data).hex() == f["encoded"]
        elif kind == "samples":
            assert encode_samples(*vectors.samples_args(f)).hex() == f["frame"]
        else:
            assert encode_header(vectors.header_info(f)).hex() == f["frame"]


def test_c_encoder_refusals(program: Program):
    res = program.run("--errors")
    passed, failed = _summary(res.stdout)
    assert res.returncode == 0 and failed == 0 and passed > 30, res.stdout.decode()


def test_c_limits_and_pen_header_match_python(program: Program):
    res = program.run("--info")
    assert res.returncode == 0, res.stderr.decode()
    info = dict(line.split(" ", 1) for line in res.stdout.decode().splitlines())
    assert int(info["max_body"]) == MAX_BODY
    assert int(info["max_frame"]) == MAX_ENCODED + 1  # + the delimiter
    # the sketch's channel table (pen_info.h) says what device/protocol/info.py says, to the bit
    assert info["pen_header"] == encode_header(pen_info()).hex()


def test_only_one_copy_of_the_encoder():
    found = sorted(p.relative_to(REPO) for p in (REPO / "device").rglob("tactile_frame.[ch]"))
    assert found == [(SRC / f"tactile_frame.{ext}").relative_to(REPO) for ext in "ch"]


def _bits(x: float) -> str:
    return f"0x{struct.unpack('<I', struct.pack('<f', x))[0]:08x}"


def _random_stream(rng: np.random.Generator) -> list[dict[str, str]]:
    """A header of random channels, then samples frames with consecutive sequence numbers
    that cross the u32 wrap, with one drop of 5 samples, in the vector file's syntax."""
    c = int(rng.integers(1, 33))
    alphabet = np.array(list("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_./-"))
    chans = []
    for i in range(c):
        name = f"c{i}_" + "".join(rng.choice(alphabet, int(rng.integers(0, 29))))
        unit = "".join(rng.choice(alphabet, int(rng.integers(0, 33))))
        scale = float(rng.choice([-1, 1]) * 10 ** rng.uniform(-8, 8))
        offset = float(rng.uniform(-1e3, 1e3)) if rng.random() < 0.5 else 0.0
        chans.append(f"{name}:{unit}:{_bits(scale)}:{_bits(offset)}")
    rate = f32(float(rng.uniform(1, 1e6)))
    header = {
        "version": str(1 if rng.random() < 0.5 else int(rng.integers(0, 256))),  # 1: decoded
        "rate_bits": _bits(rate),
        "device": "".join(rng.choice(alphabet, int(rng.integers(0, 33)))),
        "channels": ",".join(chans),
    }
    stream = [{"kind": "header", **header}]
    seq = (1 << 32) - int(rng.integers(1, 200))
    t_us = int(rng.integers(0, 1 << 32))
    for k in range(12):
        n = int(rng.integers(1, 33))
        data = rng.integers(-32768, 32768, n * c)
        data[rng.random(n * c) < 0.1] = 0  # zeros exercise the stuffing
        stream.append(
            {
                "kind": "samples",
                "seq": str(seq),
                "t_us": str(t_us),
                "channels": str(c),
                "samples": str(n),
                "data": ",".join(str(int(v)) for v in data),
            }
        )
        skip = 5 if k == 6 else 0
        seq = (seq + n + skip) % (1 << 32)
        t_us = (t_us + round((n + skip) * 1e6 / rate)) % (1 << 32)  # the clock its rate says
    return stream


def test_random_c_frames_match_python_and_decode(program: Program):
    rng = np.random.default_rng(20261123)
    streams = [_random_stream(rng) for _ in range(6)]
    lines = ["pen-header"]
    py = [encode_header(pen_info())]
    for stream in streams:
        for f in stream:
            lines.append(" ".join([f["kind"], *(f"{k}={v}" for k, v in f.items() if k != "kind")]))
            if f["kind"] == "header":
                py.append(encode_header(vectors.header_info(f)))
            else:
                py.append(encode_samples(*vectors.samples_args(f)))
    res = program.run("--encode", stdin=("\n".join(lines) + "\n").encode())
    assert res.returncode == 0, res.stderr.decode()
    assert res.stdout == b"".join(py)  # byte-identical to the Python encoder

    pos = len(py[0])
    for stream in streams:
        size = sum(len(b) for b in py[1 : 1 + len(stream)])
        del py[1 : 1 + len(stream)]
        events, stats = decode(res.stdout[pos : pos + size], mode="binary")
        pos += size
        assert stats.crc_errors == stats.malformed == stats.bytes_discarded == 0
        if vectors.header_info(stream[0]).protocol_version not in SUPPORTED_VERSIONS:
            # a version the decoder does not read: refused, reported, nothing delivered
            assert [(type(e), e.reason) for e in events] == [(Gap, "unsupported")]
            assert stats.unsupported == 1 and stats.refused == len(stream) - 1
            continue
        assert isinstance(events[0], Header)
        assert events[0].info == vectors.header_info(stream[0])
        gaps = [e for e in events if isinstance(e, Gap)]
        assert [(g.missing, g.reason) for g in gaps] == [(5, "drop")]
        got = [e for e in events if isinstance(e, Samples)]
        want = [vectors.samples_args(f) for f in stream[1:]]
        assert len(got) == len(want)
        host = got[0].seq
        assert host == want[0][0]  # the host count starts at the device's
        for g, (seq, _t_us, raw) in zip(got, want, strict=True):
            np.testing.assert_array_equal(g.raw, raw)
            assert g.seq % (1 << 32) == seq and g.seq >= host  # unwrapped past 2**32
            host = g.seq + len(raw)


def test_sanitizer_build(program: Program):
    if not program.sanitized:
        pytest.skip(program.note)
