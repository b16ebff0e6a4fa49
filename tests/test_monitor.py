"""tactile-monitor: the header, per-channel figures over the last second (against numpy on the
simulator's own samples), the link figures, --raw's bytes, the terminal redraw, the live page."""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
import urllib.request

import numpy as np
import pytest
from conftest import line_starting, page_url, read_link

from tactile.device.link import Connection
from tactile.device.protocol import (
    ChannelSpec,
    DeviceInfo,
    Header,
    Samples,
    StreamDecoder,
    encode_header,
    encode_samples,
    pen_info,
)
from tactile.device.sim import PenSimulator
from tactile.runtime import monitor
from tactile.runtime.commands.monitor import main as monitor_main
from tactile.runtime.commands.monitor import no_samples

PEN = "sim://?texture=paper&seed=1&speed=max&seconds=2"  # 200 samples, as fast as read


def scales(info: DeviceInfo) -> np.ndarray:
    return np.array([c.scale for c in info.channels], np.float64)


def last_block(out: str) -> dict[str, list[float]]:
    """The channel rows of the last plain block: name -> [value, min, max, rms]."""
    block = out.rsplit("-- ", 1)[1]
    rows = {}
    for line in block.splitlines()[2:]:
        parts = line.split()
        if len(parts) == 6:
            rows[parts[0]] = [float(x) for x in parts[1:5]]
    return rows


def read_all(monkeypatch, url: str) -> int:
    """``tactile-monitor --port url``, stopped as by Ctrl-C once it has read every byte of the
    simulated link (as many as :func:`read_link` gets): no wall-clock deadline."""
    whole = len(read_link(url.split("?", 1)[1], 7)[0])
    read, got = Connection.read, [0]

    def counted(self):
        chunk = read(self)
        before, got[0] = got[0], got[0] + len(chunk.data if chunk else b"")
        if before < whole <= got[0]:
            os.kill(os.getpid(), signal.SIGINT)  # the monitor's handler: stop after this read
        return chunk

    monkeypatch.setattr(Connection, "read", counted)
    return monitor_main(["--port", url, "--seconds", "600"])


def test_figures_are_over_the_last_second_in_units(capsys, monkeypatch):
    assert read_all(monkeypatch, PEN) == 0
    out, err = capsys.readouterr()
    assert out.startswith("tactile-pen on sim://?texture=paper&seed=1&speed=max&seconds=2: "
                          "protocol 1, 100 Hz, 8 channels: pressure_0 [N], pressure_1 [N], "
                          "accel_x [g]")
    assert "\x1b[" not in out  # not a terminal: plain lines
    raw = PenSimulator("paper", 1).read(200)
    x = raw[-100:].astype(np.float64) * scales(pen_info())  # the last second, by hand
    rows = last_block(out)
    assert list(rows) == list(pen_info().channel_names)
    for k, name in enumerate(rows):
        want = [x[-1, k], x[:, k].min(), x[:, k].max(), np.sqrt(np.mean(x[:, k] ** 2))]
        np.testing.assert_allclose(rows[name], want, rtol=6e-4, atol=1e-9)  # 4 digits shown
    link = out.rstrip().splitlines()[-1]
    assert link.startswith("link: frames 202  samples 200  crc 0  malformed 0  gaps 0 (lost 0)")
    # read as fast as it comes (speed=max): the rate is not checked here, the sanity is
    assert re.search(r"tactile-monitor: (alive and sane|too fast, otherwise sane): 200 samples "
                     r"in \d+\.\d s \([\d.]+ Hz received, 100 Hz declared", err)


def test_link_faults_are_counted_and_named(capsys, monkeypatch):
    url = "sim://?texture=paper&seed=4&speed=max&seconds=5&drop=0.05&flip=0.002"
    assert read_all(monkeypatch, url) == 0
    out, err = capsys.readouterr()
    dec = StreamDecoder()
    dec.feed(read_link(url.split("?", 1)[1], 7)[0])  # the same bytes, decoded by themselves
    st = dec.stats
    assert st.crc_errors > 0 and st.gaps > 0
    assert (f"crc {st.crc_errors}  malformed {st.malformed}  gaps {st.gaps} (lost "
            f"{st.samples_lost})") in out.rstrip().splitlines()[-1]
    assert f"{st.crc_errors} CRC errors" in err and f"{st.gaps} gap" in err
    assert re.search(r"tactile-monitor: (alive|too fast): ", err) and "sane" not in err


def verdict_of(samples: int, seconds: float) -> str:
    """The verdict on ``samples`` clean samples of the simulated pen (100 Hz declared) whose
    first bytes came ``seconds`` before the end."""
    watch, dec = monitor.Watch(), StreamDecoder()
    raw = PenSimulator("paper", 1).read(samples)
    data = encode_header(pen_info()) + b"".join(
        encode_samples(i, i * 10_000, raw[i:i + 10]) for i in range(0, samples, 10))
    watch.handle(dec.feed(data))
    watch.first_data = 1000.0
    return monitor.verdict(watch, dec, 1000.0 + seconds)


def test_the_verdict_counts_one_gap_in_the_singular():
    watch, dec = monitor.Watch(), StreamDecoder()
    raw = PenSimulator("paper", 1).read(200)
    data = encode_header(pen_info()) + b"".join(  # samples 100..109 never sent
        encode_samples(i, i * 10_000, raw[i:i + 10]) for i in range(0, 200, 10) if i != 100)
    watch.handle(dec.feed(data))
    watch.first_data = 1000.0
    assert monitor.verdict(watch, dec, 1002.0).endswith("; 1 gap (10 samples lost)")


def test_the_verdict_says_alive_only_at_about_the_declared_rate():
    assert verdict_of(202, 2.0) == ("alive and sane: 202 samples in 2.0 s (101.0 Hz received, "
                                    "100 Hz declared)")
    assert verdict_of(181, 2.0).startswith("alive and sane: ")  # 90.5 Hz: within 10%
    assert verdict_of(101, 2.0) == ("too slow, otherwise sane: 101 samples in 2.0 s (50.5 Hz "
                                    "received, 100 Hz declared: more than 10% off)")
    assert verdict_of(230, 2.0).startswith("too fast, otherwise sane: 230 samples in 2.0 s "
                                           "(115.0 Hz received")


def test_the_verdict_leaves_out_what_waited_in_the_port():
    """A pty that held 1.5 s of samples when the monitor opened it gave them at once, and the
    verdict said `too fast` (151 Hz over 3 s) of a pen at its 100 Hz; the rate now counts
    from half a second after the first bytes (the samples by then: settled)."""
    watch, dec = monitor.Watch(), StreamDecoder()
    raw = PenSimulator("paper", 1).read(450)
    watch.handle(dec.feed(encode_header(pen_info()) + b"".join(
        encode_samples(i, i * 10_000, raw[i:i + 10]) for i in range(0, 450, 10))))
    watch.first_data, watch.settled = 1000.0, (1000.5, 200)  # 150 waiting + 0.5 s at 100 Hz
    assert monitor.verdict(watch, dec, 1003.0) == (
        "alive and sane: 450 samples in 3.0 s (100.0 Hz received over the last 2.5 s, 100 Hz "
        "declared)")
    watch.settled = (1002.5, 400)  # too little after it: from the first bytes, as before
    assert monitor.verdict(watch, dec, 1003.0).startswith("too fast")


def test_the_rate_counts_from_the_first_samples_not_the_first_bytes(monkeypatch):
    """A CSV board opened mid-run without names: its rows wait 2 s for a names line, then come
    at once; counted from 0.5 s after the first bytes, the verdict said `too fast` (111 Hz
    over 5 s) of a board at 100 Hz. The rate now counts from 0.5 s after the first samples.
    The watch runs on a scripted clock: a chunk of 10 rows every 0.1 s."""
    import io
    from types import SimpleNamespace

    dec = StreamDecoder()
    now = {"t": 1000.0}
    monkeypatch.setattr(monitor.time, "monotonic", lambda: now["t"])

    def chunks():
        for k in range(50):
            now["t"] = 1000.0 + 0.1 * (k + 1)
            data = b"".join(b"%d,1,2\n" % (10 * k + i) for i in range(10))
            yield SimpleNamespace(data=data, events=dec.feed(data))

    conn = SimpleNamespace(chunks=chunks, decoder=dec, port="test", silent_for=lambda t: None)
    watch = monitor.Watch()
    monitor._watch(conn, 1.0, None, watch, monitor.Screen(io.StringIO()), 1000.0)
    # 2 s of rows held (200 lines, the first line not taken): released with the chunk at 2.1 s
    assert watch.first_samples == pytest.approx(1002.1) and watch.settled[0] == pytest.approx(
        1002.6)
    assert monitor.verdict(watch, dec, 1005.0) == (
        "alive: 499 samples in 4.9 s (100.0 Hz received over the last 2.4 s, 100 Hz declared); "
        "1 CSV line not read (a port opened mid-line cuts one)")  # (it said 0 CRC errors...)


def test_no_samples_counts_the_bytes_held_waiting_for_a_frame_end_as_not_decodable():
    """Bytes that never end a frame (a wrong device or baud rate: no zero byte, no line end)
    stay held by the decoder, and the error said '0 not decodable' of them."""
    junk = bytes(range(1, 10)) * 7  # 63 bytes, no 0x00 and no newline
    decoder = StreamDecoder()
    assert decoder.feed(junk) == [] and decoder.held == 63
    assert no_samples("sim", 2.0, decoder) == ("no samples from sim in 2.0 s (63 bytes read; "
                                               "63 not decodable)")
    decoder = StreamDecoder(mode="binary")  # a frame end with nothing decodable before it:
    decoder.feed(junk + b"\x00" + junk[:5])  # 63 thrown away, the delimiter, 5 held
    assert decoder.held == 5
    assert no_samples("sim", 1.0, decoder).endswith("(69 bytes read; 68 not decodable)")


def test_no_data_is_exit_2_and_bad_options_exit_1(capsys):
    assert monitor_main(["--port", "loop://", "--seconds", "0.3"]) == 2
    assert re.search(r"error: no samples from loop:// in \d+\.\d s \(0 bytes read; 0 not "
                     r"decodable\)", capsys.readouterr().err)
    assert monitor_main(["--port", "sim://?nonsense=1", "--seconds", "0.3"]) == 2
    assert "nonsense" in capsys.readouterr().err
    for option in (["--serve", "0"], ["--every", "5"], ["--csv-rate", "50"]):
        assert monitor_main(["--port", PEN, "--raw", *option]) == 1  # ignored, before
        assert f"--raw shows the bytes as they arrive; {option[0]} is for decoded samples" \
            in capsys.readouterr().err
    assert monitor_main(["--port", "", "--seconds", "0.3"]) == 1  # was: look for a pen
    assert "port '': must be a device path or a URL" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        monitor_main(["--port", PEN, "--seconds", "-1"])
    assert e.value.code == 1


def test_raw_shows_the_links_bytes_in_hex(capsys):
    assert monitor_main(["--port", PEN, "--raw", "--seconds", "1"]) == 0
    out = capsys.readouterr().out
    shown = bytearray()
    for n, line in enumerate(out.splitlines()):
        offset, hexes = line[:8], line[10:58]
        assert int(offset, 16) == len(shown), f"line {n}: offset"
        shown += bytes.fromhex(hexes)
        assert line[59] == "|" and line[-1] == "|"
        text = line[60:-1]
        assert text == "".join(chr(b) if 32 <= b < 127 else "." for b in shown[-len(text):])
    whole, _, _ = read_link(PEN.split("?", 1)[1], 3)  # the same link's bytes, read otherwise
    assert bytes(shown) == whole


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_terminal_gets_the_block_redrawn_in_place():
    screen = monitor.Screen(Tty())
    screen.show(["a", "b", "c"], 0.5)
    screen.show(["a", "b"], 1.0)
    assert screen.out.getvalue() == ("\x1b[2Ka\n\x1b[2Kb\n\x1b[2Kc\n\x1b[J"
                                     "\x1b[3F\x1b[2Ka\n\x1b[2Kb\n\x1b[J")
    plain = monitor.Screen(io.StringIO())
    plain.show(["a"], 1.0)
    assert plain.out.getvalue() == "-- 1.0 s\na\n"


def test_a_line_on_stderr_goes_above_the_block_not_under_its_redraw(monkeypatch, capsys):
    """On a terminal, a link line (port lost, reconnected, no data) between two redraws was
    drawn over by the next one, which also left a stale row of the block above it."""
    screen = monitor.Screen(Tty())
    monkeypatch.setattr(monitor, "_screen", screen)  # as watch_loop sets it
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # the same terminal
    screen.show(["a", "b", "c"], 0.5)
    monitor.say("port lost")
    screen.show(["a", "b"], 1.0)
    assert screen.out.getvalue() == ("\x1b[2Ka\n\x1b[2Kb\n\x1b[2Kc\n\x1b[J"
                                     "\x1b[3F\x1b[J"  # the block erased, then the line...
                                     "\x1b[2Ka\n\x1b[2Kb\n\x1b[J")  # ...and a fresh block
    assert capsys.readouterr().err == "tactile-monitor: port lost\n"
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)  # stderr to a file (2>log)
    drawn = screen.out.getvalue()
    monitor.say("port lost")
    assert screen.out.getvalue() == drawn  # the block stays as it is


def test_flat_and_saturated_channels_are_named():
    info = DeviceInfo(100.0, (ChannelSpec("tip", "N", 0.01), ChannelSpec("ax", "g", 1.0),
                              ChannelSpec("ok", "g", 1.0)))
    raw = np.zeros((50, 3), np.int16)
    raw[:, 1] = np.linspace(0, 32767, 50)
    raw[:, 2] = np.arange(50)
    w = monitor.Watch()
    w.handle([Header(info), Samples(0, 0, raw)])
    assert w.problems() == ["tip never changed (stuck at 0 counts)",
                            "ax reached the int16 limit (saturated)"]
    rows = w.channel_rows()
    assert rows[2][:5] == ("ok", "g", 49.0, 0.0, 49.0)
    assert rows[2][5] == pytest.approx(np.sqrt(np.mean(np.arange(50.0) ** 2)), rel=1e-9)


def test_the_monitor_serves_the_live_page(reap):
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.runtime.commands.monitor", "--port",
         "sim://?texture=paper&seed=1&seconds=3", "--serve", "127.0.0.1:0", "--seconds", "4"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), 120)
    url = page_url(proc.stderr)
    kinds = []
    with urllib.request.urlopen(url + "events", timeout=30) as r:
        for line in r:
            if line.startswith(b"data: "):
                obj = json.loads(line[6:])
                kinds.append(obj.get("event"))
                if obj.get("event") == "header":
                    assert obj["labels"] is False and obj["sample_rate_hz"] == 100.0
                if obj.get("event") == "end":
                    break
    # a status may come first (it is published every second from the start), then the header
    assert [k for k in kinds if k != "status"][0] == "header"
    assert "samples" in kinds and "status" in kinds
    assert kinds[-1] == "end" and None not in kinds  # no labels from the monitor
    assert proc.wait(60) == 0


@pytest.mark.parametrize("raw", [[], ["--raw"]])
def test_ctrl_c_before_any_data_is_a_stop_not_a_device_error(reap, raw):
    """A port that gives nothing (loop://): Ctrl-C after the stall message ended with 'no
    samples from loop://', exit 2, where tactile-record says it stopped, exit 0."""
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.runtime.commands.monitor", "--port", "loop://", *raw],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
    # opened, then the stall message after 2 s without data
    line = line_starting(proc.stderr, "tactile-monitor: no data for")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=20)
    assert line.startswith("tactile-monitor: no data for"), line
    assert proc.returncode == 0, err
    assert err.splitlines()[-1] == "tactile-monitor: stopped by SIGINT before any data", err
