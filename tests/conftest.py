"""Shared test helpers."""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

if TYPE_CHECKING:
    from tactile.device.sim import Injected

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
HAPMAT = SHARED / "datasets" / "hapmat" / "hapmat_stick_imu.npz"


def pen_stream(n: int, per_frame: int = 1, seed: int = 0, header_every: int = 100):
    """A clean binary stream of ``n`` samples, and the samples: (bytes, frame spans, raw (n, 8)).

    Each sample's channel 0 holds its sequence number mod 2**15, so a sample can be traced.
    ``spans`` lists (start, end, first_seq, n_samples) of every samples frame in the bytes
    (end includes the delimiter); header frames have n_samples = 0.
    """
    from tactile.device.protocol import encode_header, encode_samples, pen_info

    rng = np.random.default_rng(seed)
    raw = rng.integers(-32768, 32768, (n, 8)).astype(np.int16)
    raw[:, 0] = np.arange(n) % 32768
    out = bytearray()
    spans = []
    for s in range(0, n, per_frame):
        if header_every and s % header_every == 0:
            h = encode_header(pen_info())
            spans.append((len(out), len(out) + len(h), s, 0))
            out += h
        f = encode_samples(s, s * 10_000, raw[s : s + per_frame])
        spans.append((len(out), len(out) + len(f), s, len(raw[s : s + per_frame])))
        out += f
    return bytes(out), spans, raw


@pytest.fixture
def reap():
    """``reap(proc, seconds=60)``: kill a test's subprocess after ``seconds`` (a blocking read
    of its output then ends, and the test fails instead of hanging) and, at the end of the
    test, if it is still running."""
    watched: list[tuple[subprocess.Popen, threading.Timer]] = []

    def watch(proc: subprocess.Popen, seconds: float = 60) -> subprocess.Popen:
        timer = threading.Timer(seconds, proc.kill)
        timer.start()
        watched.append((proc, timer))
        return proc

    yield watch
    for proc, timer in watched:
        timer.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def start_and_signal(entry: str, args: list[str], sig: int) -> tuple[int, str, str]:
    """Start a console entry point (``tactile.cli:<entry>``) in a subprocess, send ``sig`` the
    moment it handles SIGTERM (Python itself handles only SIGINT, so that is when the entry
    point's start-up handlers are in place, before its imports: the signal lands while it
    imports numpy and onnxruntime), and return (exit code, stdout, stderr). Linux only: it
    reads the caught-signal mask in ``/proc/<pid>/status``. ``entry`` may also name its module:
    ``<module>:<function>``."""
    module, _, name = entry.rpartition(":")
    code = f"import sys; from {module or 'tactile.cli'} import {name}; sys.exit({name}())"
    proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    status = Path(f"/proc/{proc.pid}/status")
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and proc.poll() is None:
        caught = next((ln for ln in status.read_text().splitlines() if ln.startswith("SigCgt:")),
                      "SigCgt: 0")
        if int(caught.split()[1], 16) >> (15 - 1) & 1:  # SIGTERM is signal 15
            break
        time.sleep(0.001)
    try:
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:  # it did not stop: fail, without leaving it running
            proc.kill()
            proc.wait()
    return proc.returncode, out, err


def read_link(query: str, chunk: int) -> tuple[bytes, Injected, list[int]]:
    """Read a whole link the way the sim:// port does: ask for what is due, ``chunk`` samples
    more each time, and replug the pen when it is unplugged (as a reader that reconnects at
    once). Returns the bytes, the link's counts and the sizes of the frames."""
    from tactile.device.protocol import Samples, StreamDecoder
    from tactile.device.sim import LinkConfig, PenLink

    link = PenLink(LinkConfig.from_query(query))
    data, due, sizes = b"", 0, []
    dec = StreamDecoder()
    while not link.finished:
        out_for = link.unplug_due()
        if out_for is not None:
            link.restart(link.stream_time + out_for)
            continue
        due = max(due, link.sim.n_read) + chunk
        got = link.produce(max(0, due - link.sim.n_read))
        sizes += [len(ev.raw) for ev in dec.feed(got) if isinstance(ev, Samples)]
        data += got
    return data, link.injected, sizes


def page_url(stderr) -> str:
    """The live page's address, from the first 'live page at URL' line of a subprocess's stderr
    (a text pipe), whatever lines come before it; fails if stderr ends without one."""
    for line in stderr:
        m = re.search(r"live page at (http://\S+/)", line)
        if m:
            return m[1]
    pytest.fail("stderr ended without saying where the live page is")


def line_starting(stderr, prefix: str, most: int = 20) -> str:
    """The first of at most ``most`` lines of a subprocess's stderr (a text pipe) that starts
    with ``prefix``; else the last line read ('' at its end), which the caller's assertion
    shows. Reading waits for the line, not for a time."""
    line = ""
    for _ in range(most):
        line = stderr.readline()
        if not line or line.startswith(prefix):
            break
    return line


def not_utf8(data: bytes, text: bytes, nth: int = 0, offset: int = 5) -> bytes:
    """``data`` (a file's bytes) with byte ``offset`` of the nth occurrence of ``text`` made
    0xd0: a string of the file that is no longer UTF-8, as in a damaged copy; the length is
    unchanged."""
    at = -1
    for _ in range(nth + 1):
        at = data.index(text, at + 1)
    return data[: at + offset] + b"\xd0" + data[at + offset + 1 :]


def rows_in(folder: Path) -> int:
    """Complete data rows in the one CSV being written in ``folder`` (0 before it exists)."""
    csvs = list(folder.glob("*.csv"))
    if not csvs:
        return 0
    text = csvs[0].read_bytes()
    return sum(1 for ln in text[: text.rfind(b"\n") + 1].splitlines()[1:]
               if not ln.startswith(b"#"))


def listening() -> tuple[socket.socket, str]:
    """A TCP server on 127.0.0.1 (a device behind ``socket://``) and its URL; its accept()
    fails after 30 s rather than hangs."""
    srv = socket.socket()
    srv.settimeout(30)
    srv.bind(("127.0.0.1", 0))
    srv.listen()
    return srv, f"socket://127.0.0.1:{srv.getsockname()[1]}"
