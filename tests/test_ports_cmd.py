"""tactile-ports (the listing and its pen rule, the one tactile-run uses), tactile-record's
auto-detected port, and the library calls tactile.runtime.labels() and to_units()."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading

import numpy as np
import pytest
from conftest import REPO

from tactile.device.commands import ports as ports_cmd
from tactile.device.link import portlist
from tactile.errors import DeviceError

MODEL = REPO / "models" / "pen-exp2.onnx"


class FakePort:
    """What ``serial.tools.list_ports.comports()`` lists."""

    def __init__(self, device, vid=None, pid=None, serial_number=None, description="n/a",
                 manufacturer=None):
        self.device, self.vid, self.pid = device, vid, pid
        self.serial_number, self.description = serial_number, description
        self.manufacturer = manufacturer


@pytest.fixture
def attached(monkeypatch):
    from serial.tools import list_ports

    ports: list[FakePort] = []
    monkeypatch.setattr(list_ports, "comports", lambda: list(ports))
    return ports


def test_the_listing_marks_what_find_port_would_take(attached, capsys):
    attached += [FakePort("/dev/ttyS0", description="ttyS0"),
                 FakePort("/dev/ttyACM0", 0x2886, 0x8045, "A1B2C3", "XIAO nRF52840", "Seeed")]
    assert ports_cmd.main(["--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == [
        {"device": "/dev/ttyACM0", "description": "XIAO nRF52840", "vid_pid": "2886:8045",
         "serial_number": "A1B2C3", "manufacturer": "Seeed", "likely_pen": True},
        {"device": "/dev/ttyS0", "description": "ttyS0", "vid_pid": None,
         "serial_number": None, "manufacturer": None, "likely_pen": False}]
    assert err == "tactile-ports: one likely pen: /dev/ttyACM0 (taken when --port is " \
                  "omitted)\n"
    assert portlist.find_port() == "/dev/ttyACM0"
    from tactile.runtime import runner

    assert runner.find_port is portlist.find_port  # tactile-run's rule is this one
    assert ports_cmd.main([]) == 0
    out, _ = capsys.readouterr()
    assert out.splitlines() == [
        "DEVICE        VID:PID    SERIAL  PEN  DESCRIPTION",
        "/dev/ttyACM0  2886:8045  A1B2C3  yes  XIAO nRF52840",
        "/dev/ttyS0    -          -       no   ttyS0"]


@pytest.mark.parametrize("devices, says", [
    ([], "no serial ports found"),
    (["/dev/ttyS0"], "no likely pen (no USB serial device): give --port"),
    (["/dev/ttyUSB0", "/dev/ttyACM1"], "2 likely pens: give --port"),
])
def test_what_it_says_when_there_is_not_exactly_one_pen(attached, capsys, devices, says):
    attached += [FakePort(d) for d in devices]
    assert ports_cmd.main([]) == 0
    assert capsys.readouterr().err == f"tactile-ports: {says}\n"
    with pytest.raises(DeviceError, match="likely pen found; give --port"):
        portlist.find_port()


def test_tactile_record_takes_the_one_likely_pen(attached, tmp_path, capsys, monkeypatch):
    from tactile.device.commands import record as recorder
    from tactile.device.recordings import read_take

    url = "sim://?texture=paper&seed=1&speed=max&seconds=1"
    attached.append(FakePort(url, vid=0x2886))  # a sim:// URL in the device's place
    monkeypatch.setattr(signal, "signal", lambda *a: signal.SIG_DFL)  # leave pytest's alone
    assert recorder.main(["--label", "paper", "--out", str(tmp_path), "--seconds", "1"]) == 0
    take = read_take(capsys.readouterr().out.strip())
    assert take.meta["source"] == url and len(take.seq) == 100
    attached.clear()
    assert recorder.main(["--label", "paper", "--out", str(tmp_path)]) == 2
    assert "no likely pen found; give --port" in capsys.readouterr().err


def test_labels_in_one_call_are_tactile_runs_labels():
    from tactile.runtime import labels

    url = "sim://?texture=paper&seed=3&speed=max&seconds=6&drop=0.01"
    proc = subprocess.Popen([sys.executable, "-m", "tactile.runtime.commands.run", "--model",
                             str(MODEL), "--port", url], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    timer = threading.Timer(120, proc.kill)  # a stuck run fails the test instead of hanging it
    timer.start()
    printed = []
    try:  # the first 12 labels and the events before them, however long they take to come
        while sum("label" in o for o in printed) < 12 and (line := proc.stdout.readline()):
            printed.append(json.loads(line))
    finally:
        proc.kill()
        proc.wait()
        timer.cancel()
    want = [o for o in printed if "label" in o]
    assert len(want) == 12
    gaps: list[int] = []
    got = []

    def note(kind: str, f: dict) -> None:
        if kind == "gap":  # a stall (a loaded machine) has no seq
            gaps.append(f["seq"])

    for lab in labels(url, MODEL, on_event=note):
        got.append(lab.to_dict())
        if len(got) == len(want):
            break  # closes the port
    for a, b in zip(got, want, strict=True):
        assert (a["seq"], a["label"]) == (b["seq"], b["label"])
        assert a["probs"] == pytest.approx(b["probs"], abs=1e-6)
    last = want[-1]["seq"]
    printed_gaps = [o["seq"] for o in printed if o.get("event") == "gap" and o["seq"] <= last]
    assert [g for g in gaps if g <= last] == printed_gaps and printed_gaps


def test_to_units_is_counts_times_scale_plus_offset():
    from tactile.device.protocol import ChannelSpec, DeviceInfo
    from tactile.runtime import to_units

    info = DeviceInfo(100.0, (ChannelSpec("a", "N", 0.5, 1.0), ChannelSpec("b", "g", -2.0)))
    got = to_units(info, np.array([[2, 3], [-4, 0]], np.int16))
    assert got.dtype == np.float32 and got.tolist() == [[2.0, -6.0], [-1.0, 0.0]]
