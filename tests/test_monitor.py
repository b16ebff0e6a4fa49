"""tactile-monitor: the header, per-channel figures over the last second (against numpy on the
simulator's own samples), the link figures, --raw's bytes, the terminal redraw, the live page."""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
import urllib.request

import numpy as np
import pytest
from conftest import read_link

from tactile.device.decoder import Header, Samples, StreamDecoder
from tactile.device.info import ChannelSpec, DeviceInfo, pen_info
from tactile.device.simulator import PenSimulator
from tactile.runtime import monitor

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


def test_figures_are_over_the_last_second_in_units(capsys):
    assert monitor.main(["--port", PEN, "--seconds", "1.5"]) == 0
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
    assert re.search(r"tactile-monitor: alive and sane: 200 samples in \d+\.\d s", err)


def test_link_faults_are_counted_and_named(capsys):
    url = "sim://?texture=paper&seed=4&speed=max&seconds=5&drop=0.05&flip=0.002"
    assert monitor.main(["--port", url, "--seconds", "1.5"]) == 0
    out, err = capsys.readouterr()
    dec = StreamDecoder()
    dec.feed(read_link(url.split("?", 1)[1], 7)[0])  # the same bytes, decoded by themselves
    st = dec.stats
    assert st.crc_errors > 0 and st.gaps > 0
    assert (f"crc {st.crc_errors}  malformed {st.malformed}  gaps {st.gaps} (lost "
            f"{st.samples_lost})") in out.rstrip().splitlines()[-1]
    assert f"{st.crc_errors} CRC errors" in err and f"{st.gaps} gaps" in err
    assert "alive:" in err and "sane" not in err


def test_no_data_is_exit_2_and_bad_options_exit_1(capsys):
    assert monitor.main(["--port", "loop://", "--seconds", "0.3"]) == 2
    assert re.search(r"error: no samples from loop:// in 0\.\d s \(0 bytes read; 0 not "
                     r"decodable\)", capsys.readouterr().err)
    assert monitor.main(["--port", "sim://?nonsense=1", "--seconds", "0.3"]) == 2
    assert "nonsense" in capsys.readouterr().err
    assert monitor.main(["--port", PEN, "--raw", "--serve", "0"]) == 1
    with pytest.raises(SystemExit) as e:
        monitor.main(["--port", PEN, "--seconds", "-1"])
    assert e.value.code == 1


def test_raw_shows_the_links_bytes_in_hex(capsys):
    assert monitor.main(["--port", PEN, "--raw", "--seconds", "1"]) == 0
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
        [sys.executable, "-m", "tactile.runtime.monitor", "--port",
         "sim://?texture=paper&seed=1&seconds=3", "--serve", "127.0.0.1:0", "--seconds", "4"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), 120)
    url = re.search(r"live page at (http://\S+/)", proc.stderr.readline())[1]
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
    assert kinds[0] == "header" and "samples" in kinds and "status" in kinds
    assert kinds[-1] == "end" and None not in kinds  # no labels from the monitor
    assert proc.wait(60) == 0
