"""Ports: bytes read before an unplug are kept, a port is used by one program, and a reconnection
goes only to the same pen. Sockets on 127.0.0.1 and ptys; every wait is for an event."""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
import serial
from conftest import REPO, listening, rows_in

import tactile.device  # noqa: F401  (registers sim://)
from tactile.device.link import PenId, PortBusy, open_port, read_some, reconnect
from tactile.device.protocol import (
    ChannelSpec,
    DeviceInfo,
    Header,
    StreamDecoder,
    encode_header,
    encode_samples,
    pen_info,
)
from tactile.device.sim import LinkConfig, PenLink, PenSimulator

SHIPPED = REPO / "models" / "pen-exp2.onnx"
TCP_CLOSE_WAIT = 8  # tcp_info.tcpi_state once the peer's FIN has arrived


def stop_listening(srv: socket.socket) -> None:
    """Close a listening socket, waking a thread blocked in its accept() (close alone does
    not: the socket would go on taking connections until accept's timeout)."""
    try:
        srv.shutdown(socket.SHUT_RDWR)
    except OSError:  # already closed
        pass
    srv.close()


def until(condition, what: str, seconds: float = 30) -> None:
    """Poll ``condition()`` until true; fail after ``seconds`` (a deadline, not a delay)."""
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"never happened: {what}")
        time.sleep(0.001)


def peer_closed(link) -> bool:
    """The server's data and its FIN have both reached ``link``'s socket (TCP delivers in
    order, so everything sent before the FIN is in the receive queue)."""
    s = socket.socket(fileno=os.dup(link.fileno()))
    try:
        return s.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 1)[0] == TCP_CLOSE_WAIT
    finally:
        s.close()


def test_bytes_read_before_a_disconnect_are_kept():
    """Data then a disconnect, both waiting before the read: pyserial's read(4096) raises and
    drops the data it had read; read_some hands the data over, then reports the loss."""
    srv, url = listening()
    data = bytes(range(1, 256)) * 8  # 2040 B, less than one read
    try:
        for way in ("pyserial", "read_some"):
            link = open_port(url, 115200)
            conn, _ = srv.accept()
            conn.sendall(data)
            conn.close()
            until(lambda link=link: peer_closed(link), "the FIN arrived")
            if way == "pyserial":  # the fault, reproduced: what the loops did before
                link.timeout = 0.05
                with pytest.raises(serial.SerialException, match="disconnected"):
                    link.read(4096)
            else:
                got, lost = bytearray(), None
                while lost is None:
                    chunk, lost = read_some(link)
                    got += chunk
                assert bytes(got) == data and isinstance(lost, serial.SerialException)
            link.close()
    finally:
        srv.close()


def test_bytes_that_arrive_while_the_port_opens_are_kept(monkeypatch):
    """A device that sends as soon as the link is up (a pen behind a TCP bridge, the burst it
    held while the link was down): pyserial's open() ends by discarding the input that has
    arrived, and the recorder lost those samples (after a reconnection, the pen's header too).
    Here the server's whole burst and its FIN are in the socket before open() reaches that
    step (it waits for them inside open, after connecting)."""
    from serial.urlhandler import protocol_socket

    srv, url = listening()
    data = encode_header(pen_info()) + bytes(range(256)) * 4
    configure = protocol_socket.Serial._reconfigure_port

    def connected_then_burst(self, *args, **kwargs):
        conn, _ = srv.accept()
        conn.sendall(data)
        conn.close()
        until(lambda: peer_closed(self), "the burst and the FIN arrived")
        return configure(self, *args, **kwargs)

    monkeypatch.setattr(protocol_socket.Serial, "_reconfigure_port", connected_then_burst)
    try:
        link = open_port(url, 115200)
        got, lost = bytearray(), None
        while lost is None:
            chunk, lost = read_some(link)
            got += chunk
        link.close()
    finally:
        srv.close()
    assert bytes(got) == data


def test_bytes_waiting_on_a_device_when_it_opens_are_kept():
    """The same on a device (here a pty; a USB or UART pen alike): pyserial's posix open()
    flushes the input queue (tcflush), so what a pen sent before the port was open (its
    header, as it boots when plugged in) was lost."""
    import tty

    master, slave = os.openpty()
    try:
        tty.setraw(slave)  # the bytes go in as they are (no line editing, no signals)
        data = encode_header(pen_info()) + bytes(range(256)) * 2
        os.write(master, data)
        link = open_port(os.ttyname(slave), 115200)
        got = bytearray()
        while len(got) < len(data):
            chunk, lost = read_some(link, wait=5)
            assert chunk and lost is None, (len(got), lost)  # no more arrives: all was there
            got += chunk
        link.close()
    finally:
        os.close(master)
        os.close(slave)
    assert bytes(got) == data


def test_a_port_is_opened_by_one_program_and_the_holder_is_named(tmp_path):
    """The same pty twice: the second open is refused, naming the holder (here this process),
    and a second tactile-run on it exits 2 in one line naming the first one's pid."""
    master, slave = os.openpty()
    name = os.ttyname(slave)
    first = open_port(name, 115200)
    try:
        with pytest.raises(PortBusy, match=rf"cannot open {name}: in use by .*pid {os.getpid()}"):
            open_port(name, 115200)
    finally:
        first.close()
    runner = subprocess.Popen(
        [sys.executable, "-m", "tactile.runtime.commands.run", "--model", str(SHIPPED),
         "--port", name, "--raw"],  # --raw: its first stderr line is the port's
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = runner.stderr.readline()
        assert line.startswith(f"tactile-run: opened {name}"), line
        proc = subprocess.run([sys.executable, "-m", "tactile.runtime.commands.run", "--model",
                               str(SHIPPED), "--port", name, "--wait", "--raw"],
                              capture_output=True, text=True, timeout=60)
    finally:
        runner.send_signal(signal.SIGINT)
        runner.communicate(timeout=30)
        os.close(master)
        os.close(slave)
    assert proc.returncode == 2 and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"cannot open {name}: in use by pid {runner.pid} (" in lines[0], \
        proc.stderr


def stream(conn: socket.socket, chunks, done: threading.Event) -> None:
    """Send ``chunks`` (an iterator of bytes) until the peer goes or ``done`` is set: a device
    that keeps talking, so what a socket:// open discards at its start does not matter."""
    with conn:
        for chunk in chunks:
            try:
                conn.sendall(chunk)
            except OSError:  # the client closed it
                return
            if done.wait(0.01):
                return


def other_device():
    other = encode_header(pen_info(device="other-pen"))
    while True:
        yield other


def pen(seed: int):
    link = PenLink(LinkConfig(texture="paper", seed=seed))
    while True:
        yield link.produce(10)


def test_after_an_unplug_only_the_same_pen_is_taken_back(reap):
    """The pen sends 300 samples and vanishes; another device answers on its name (here the
    same TCP port) and is refused; then the pen comes back and labels resume. The 300 samples
    that arrived with the disconnect are all labelled (11 windows)."""
    srv, url = listening()
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.runtime.commands.run", "--model", str(SHIPPED),
         "--port", url, "--stall-timeout", "600", "--status-every", "600", "--raw"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), 120)
    role = {"now": "other"}
    done = threading.Event()

    def serve() -> None:  # every later connection: the other device, then the pen
        while not done.is_set():
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            stream(conn, other_device() if role["now"] == "other" else pen(5), done)

    server = threading.Thread(target=serve, daemon=True)
    try:
        conn, _ = srv.accept()
        err = [proc.stderr.readline()]
        assert err[0].startswith(f"tactile-run: opened {url}"), err
        conn.sendall(PenLink(LinkConfig(texture="paper", seed=2)).produce(300))
        conn.close()  # the unplug: the data and the disconnect arrive together
        server.start()
        while "is not the pen" not in err[-1]:
            err.append(proc.stderr.readline())
            assert err[-1], err
        role["now"] = "pen"
        labels, events = [], []
        while not (labels and labels[-1][0] > 0):  # until a label after the reconnection
            line = proc.stdout.readline()
            assert line, (labels, events, err)
            x = json.loads(line)
            if "event" in x:
                events.append(x["event"])
            else:
                labels.append((len(events), x["seq"]))
        proc.send_signal(signal.SIGINT)
        proc.stdout.read()  # to its end, through the pipes readline() buffered
        rest = proc.stderr.read()
        proc.wait(timeout=30)
    finally:
        done.set()
        stop_listening(srv)
        server.join(30) if server.is_alive() else None
    err = "".join(err) + rest
    assert proc.returncode == 0, err
    assert f"{url} is not the pen: device 'other-pen', not 'tactile-pen'" in err
    assert f"reconnected to {url}" in err
    assert events[0] == "reconnect" and set(events[1:]) <= {"gap"}, events  # restart gap
    before = [seq for n, seq in labels if n == 0]
    assert before == list(range(49, 300, 25))  # every window of the 300 samples
    summary = json.loads(rest.split("tactile-run: summary ", 1)[1].splitlines()[0])
    assert summary["reconnects"] == 1


class _FakePort:
    def __init__(self, device: str, serial_number: str | None):
        self.device, self.serial_number = device, serial_number
        self.vid, self.description = 0x2341, "pen"


def test_the_pen_is_found_again_by_its_usb_serial_number(monkeypatch):
    """Its old name is gone; of the devices listed, the one with its serial number but another
    header is refused, one with another serial number is not even opened (it could not be),
    and the one with its serial number and its header is taken."""
    from serial.tools import list_ports

    pen_url = "sim://?texture=paper&seed=1&speed=max&seconds=5"
    listed = [_FakePort("sim://?texture=velvet", "OTHER"),  # opening it would raise
              _FakePort("sim://?texture=paper&speed=max&rate=50", "PEN1"),
              _FakePort(pen_url, "PEN1")]
    monkeypatch.setattr(list_ports, "comports", lambda: listed)
    said: list[str] = []
    got = reconnect("/dev/no-such-pen", 115200, PenId(pen_info(), "PEN1"), StreamDecoder,
                    {"flag": False}, said.append, time.monotonic() + 60)
    assert got is not None, said
    link, name, early = got
    link.close()
    assert name == pen_url
    assert [ev.info for ev in StreamDecoder().feed(early) if isinstance(ev, Header)] == \
        [pen_info()]  # the probe's bytes come back to be decoded: nothing read is lost
    assert any("rate=50 is not the pen: rate 50 Hz" in m for m in said), said
    assert said[-1] == f"reconnected to {pen_url}"


def test_an_auto_detected_pen_is_looked_for_again(monkeypatch):
    from serial.tools import list_ports

    pen_url = "sim://?texture=desk&seed=2&speed=max&seconds=5"
    monkeypatch.setattr(list_ports, "comports", lambda: [_FakePort(pen_url, None)])
    got = reconnect("/dev/no-such-pen", 115200, PenId(pen_info()), StreamDecoder,
                    {"flag": False}, lambda m: None, time.monotonic() + 60, detect=True)
    assert got is not None and got[1] == pen_url
    got[0].close()


def test_what_makes_the_same_pen():
    base = pen_info()
    assert PenId(base).differs(pen_info()) is None
    assert PenId(None).differs(pen_info(device="x")) is None  # no header yet: nothing to check
    assert "device 'x'" in PenId(base).differs(pen_info(device="x"))
    assert "rate 50 Hz" in PenId(base).differs(pen_info(50.0))
    scaled = DeviceInfo(100.0, (ChannelSpec("pressure_0", "N", 0.02), *base.channels[1:]),
                        "tactile-pen")
    assert "other units or scales" in PenId(base).differs(scaled)

    def csv(*names):
        return DeviceInfo(100.0, tuple(ChannelSpec(n, "") for n in names), "csv")

    # a CSV device sends no header: the same number of channels at the same rate is the pen
    assert PenId(csv("a", "b", "c")).differs(csv("ch0", "ch1", "ch2")) is None
    assert "2 CSV channels, not 3" in PenId(csv("a", "b", "c")).differs(csv("a", "b"))
    assert "not the 'csv' one" in PenId(csv("a", "b", "c")).differs(base)


def test_the_recorder_keeps_the_bytes_that_came_with_a_disconnect(tmp_path, reap):
    """tactile-record on a socket pen that sends 3 s of samples and hangs up at once: the take
    holds all 300 (they arrived together with the disconnect)."""
    from tactile.device.recordings import read_take

    srv, url = listening()
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.device.commands.record", "--port", url, "--label", "paper",
         "--out", str(tmp_path), "--seconds", "3"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), 120)
    try:
        conn, _ = srv.accept()
        with conn:  # sent once it says it opened the port: its socket:// open is over
            assert proc.stderr.readline() == f"tactile-record: opened {url}\n"
            conn.sendall(PenLink(LinkConfig(texture="paper", seed=2)).produce(300))
        out, err = proc.communicate(timeout=60)
    finally:
        srv.close()
    assert proc.returncode == 0, err
    take = read_take(out.strip())
    assert list(take.seq) == list(range(300))


# -- every command reads through one loop: the same pen, and only it, for each ------------------


def other_pen():
    """Another device: its own header ('other-pen', channels and rate as the pen's, so the
    model's contract does not refuse it) and samples, for as long as it is read."""
    info, raw = pen_info(device="other-pen"), PenSimulator("desk", 9).read(100)
    for seq in itertools.count(0, 10):  # 10 samples a chunk, the header every 100
        yield (encode_header(info) if seq % 100 == 0 else b"") + b"".join(
            encode_samples(s, s * 10_000, raw[s % 100 : s % 100 + 1]) for s in range(seq, seq + 10))


class InTurn:
    """A device behind a TCP port, unplugged and replugged: connection k gets ``devices[k]``
    (the last one for every later connection): ``"pen"`` until :attr:`unplug` is set,
    ``"other"`` (another device on the same name), ``"pen again"`` (the pen, rebooted). Each is
    served until the client hangs up on it (or the first pen is unplugged); :attr:`log` says
    which device each connection got, in order."""

    def __init__(self, devices: tuple[str, ...] = ("pen", "other", "pen again")) -> None:
        self.devices = devices
        self.srv, self.url = listening()
        self.unplug, self.done = threading.Event(), threading.Event()
        self.log: list[str] = []
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _first(self):
        for chunk in pen(2):
            if self.unplug.is_set():
                return
            yield chunk

    def _serve(self) -> None:
        while not self.done.is_set():
            try:
                conn, _ = self.srv.accept()
            except OSError:
                return
            name = self.devices[min(len(self.log), len(self.devices) - 1)]
            self.log.append(name)
            chunks = {"pen": self._first, "other": other_pen, "pen again": lambda: pen(5)}[name]
            stream(conn, chunks(), self.done)

    def hang_up(self) -> None:
        """Stop listening: connections to :attr:`url` are refused from now on."""
        stop_listening(self.srv)

    def close(self) -> None:
        self.done.set()
        self.hang_up()
        self.thread.join(30)


def test_labels_take_back_the_same_pen_only():
    """tactile.runtime.labels(): the pen, unplugged once a label came; another device answers on
    its name and is refused (here it sends samples its model would label); the pen comes back
    and labels resume after a reconnect event."""
    from tactile.runtime import labels

    dev = InTurn()
    events, after = [], []
    try:
        for lab in labels(dev.url, SHIPPED, seconds=120,
                          on_event=lambda kind, f: events.append(kind)):
            if "reconnect" not in events:
                dev.unplug.set()  # a label came: pull the cable
                continue
            after.append(lab)
            break
    finally:
        dev.close()
    assert after, (events, dev.log)
    # the label after the reconnection is the pen's: the other device was hung up on
    assert dev.log[:3] == ["pen", "other", "pen again"], dev.log
    assert events.count("reconnect") == 1 and set(events) <= {"reconnect", "gap", "stall",
                                                               "change"}  # the stable label's


def test_the_monitor_takes_back_the_same_pen_only(reap):
    """tactile-monitor: the same story. Its header line names the pen once (the other device
    never shows), its link line counts one reconnection, and the samples go on after it."""
    dev = InTurn()
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.runtime.commands.monitor", "--port", dev.url,
         "--every", "0.1", "--stall-timeout", "600"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), 120)
    out, since = [], None
    try:
        for line in proc.stdout:  # a block every 0.1 s; its link line is the last one
            out.append(line)
            m = re.match(r"link: frames \d+  samples (\d+) .*  reconnects (\d+)", line)
            if m is None:
                continue
            samples, reconnects = int(m[1]), int(m[2])
            if any(" on socket://" in ln for ln in out):  # the pen's header came: pull the
                dev.unplug.set()  # cable (before it, nothing tells one device from another)
            since = samples if reconnects and since is None else since
            if since is not None and samples >= since + 100:  # 1 s of samples after it
                break
        proc.send_signal(signal.SIGINT)
        rest, err = proc.communicate(timeout=60)
    finally:
        dev.close()
    out = "".join(out) + rest
    assert proc.returncode == 0, err
    assert since is not None, (out[-2000:], err)
    assert dev.log[:3] == ["pen", "other", "pen again"], dev.log
    heads = [ln for ln in out.splitlines() if " on socket://" in ln]
    assert len(heads) == 1 and heads[0].startswith(f"tactile-pen on {dev.url}: "), heads
    assert f"tactile-monitor: {dev.url} is not the pen: device 'other-pen', not " \
           "'tactile-pen'" in err, err
    assert f"tactile-monitor: reconnected to {dev.url}" in err, err


def test_the_recorder_finds_an_auto_detected_pen_under_its_new_name(tmp_path, monkeypatch,
                                                                    capsys):
    """tactile-record with no --port: the one likely pen is taken; it is unplugged once the take
    holds a row, and comes back under another name (its old one is gone for good). The take
    goes on there, after a restart gap, to its 300 samples."""
    from serial.tools import list_ports

    from tactile.device.commands.record import main as record_main
    from tactile.device.recordings import read_take

    first, second = InTurn(), InTurn(("pen again",))
    listed = [_FakePort(first.url, None)]
    monkeypatch.setattr(list_ports, "comports", lambda: list(listed))

    def unplug() -> None:  # once the take holds a row: the first name vanishes, a new one comes
        until(lambda: rows_in(tmp_path) > 0, "a row in the take", 60)
        first.unplug.set()
        listed[:] = [_FakePort(second.url, None)]
        first.hang_up()  # connections to the old name are refused from now on

    helper = threading.Thread(target=unplug, daemon=True)
    helper.start()
    guard = threading.Timer(120, os.kill, (os.getpid(), signal.SIGINT))  # fails, not hangs
    guard.start()
    try:
        code = record_main(["--label", "paper", "--out", str(tmp_path), "--seconds", "3"])
    finally:
        guard.cancel()
        first.close()
        second.close()
        helper.join(30)
    out, err = capsys.readouterr()
    assert code == 0, err
    assert f"reconnected to {second.url}" in err and "reconnects 1" in err, err
    take = read_take(out.strip())
    assert len(take.seq) == 300 and take.meta["complete"]
    assert [g["reason"] for g in take.meta["gaps"]] == ["restart"], take.meta["gaps"]



def test_when_its_old_name_shows_another_device_the_pen_is_looked_for_among_the_likely_pens(
        monkeypatch):
    """--port given (no auto-detection): the old name now answers with another device (a
    50 Hz one); the pen is then looked for among the likely pens listed, and found."""
    from serial.tools import list_ports

    old = "sim://?texture=paper&speed=max&rate=50"
    pen_url = "sim://?texture=desk&seed=2&speed=max&seconds=5"
    monkeypatch.setattr(list_ports, "comports", lambda: [_FakePort(pen_url, None)])
    said: list[str] = []
    got = reconnect(old, 115200, PenId(pen_info()), StreamDecoder, {"flag": False},
                    said.append, time.monotonic() + 60)
    assert got is not None, said
    got[0].close()
    assert got[1] == pen_url
    assert said[0].startswith(f"{old} is not the pen: rate 50 Hz"), said


def test_a_device_listed_with_another_usb_serial_number_is_not_opened(monkeypatch):
    """The old name is listed with another serial number: refused without opening it (opening
    this one would raise), and the pen is found by its own number."""
    from serial.tools import list_ports

    old = "sim://?texture=velvet"  # not a texture: opening it raises
    pen_url = "sim://?texture=paper&seed=1&speed=max&seconds=5"
    monkeypatch.setattr(list_ports, "comports",
                        lambda: [_FakePort(old, "OTHER"), _FakePort(pen_url, "PEN1")])
    said: list[str] = []
    got = reconnect(old, 115200, PenId(pen_info(), "PEN1"), StreamDecoder, {"flag": False},
                    said.append, time.monotonic() + 60)
    assert got is not None and got[1] == pen_url, said
    got[0].close()
    assert said[0] == f"{old} is not the pen: USB serial number OTHER, not PEN1; still looking"


def test_without_reconnect_a_loss_comes_after_the_bytes_that_came_with_it():
    """A Connection that does not reconnect: the samples that arrived with the disconnect are
    decoded, then a Lost event; the next read raises a one-line DeviceError."""
    from tactile.device.link import Connection, LinkSettings, Lost
    from tactile.device.protocol import Samples
    from tactile.errors import DeviceError

    srv, url = listening()
    try:
        conn = Connection(LinkSettings(url, reconnect=False), StreamDecoder())
        conn.open()
        peer, _ = srv.accept()
        with peer:
            peer.sendall(PenLink(LinkConfig(texture="paper", seed=2)).produce(300))
        events: list = []
        while not any(isinstance(ev, Lost) for ev in events):
            events += conn.read().events
        with pytest.raises(DeviceError, match=rf"^{re.escape(url)}: lost \("):
            conn.read()
    finally:
        srv.close()
    assert isinstance(events[-1], Lost)
    assert sum(len(ev.raw) for ev in events if isinstance(ev, Samples)) == 300


def test_a_reopened_csv_board_without_names_is_known_by_its_width():
    """The probe of a reopened port waited for a header, which a CSV board opened mid-run now
    gives only with its names line or after 2 s of rows: a board without names (or one slow to
    boot) was never taken back ("no header in 3.0 s"). Rows of the pen's width at its rate
    are enough (a CSV device is known by those); another width is another device."""
    from tactile.device.link.ports import PenId, probe
    from tactile.device.protocol import ChannelSpec, DeviceInfo, StreamDecoder

    class Board:  # a CSV board: 60 rows (under the names wait's 200), no names line
        def __init__(self, width):
            self.width, self.sent = width, 0

        def fileno(self):
            raise AttributeError

        def read(self, limit):
            n = min(20, 60 - self.sent)
            rows = b"".join(b",".join(b"%d" % (i + k) for k in range(self.width)) + b"\n"
                            for i in range(self.sent, self.sent + n))
            self.sent += n
            return rows

        def close(self):
            pass

    pen = PenId(DeviceInfo(100.0, tuple(ChannelSpec(f"ch{i}", "") for i in range(3)), "csv"))
    got = probe(Board(3), pen, lambda: StreamDecoder(csv_rate_hz=100.0), {"flag": False})
    assert got.why is None and got.data.startswith(b"0,1,2\n")
    got = probe(Board(4), pen, lambda: StreamDecoder(csv_rate_hz=100.0), {"flag": False})
    assert got.why == "4 CSV channels, not 3" and got.other


@pytest.mark.parametrize("url", ["socket://127.0.0.1:99999", "socket://", "socket://h:x",
                                 "socket://:80"])
def test_a_socket_url_without_host_and_port_is_one_line_naming_the_form(url):
    """pyserial's own line for these named nothing ('debug|info|warning|error', or "'<=' not
    supported between instances of 'int' and 'NoneType'"): a bad URL never opens, exit 2."""
    from tactile.device.link import open_port
    from tactile.errors import DeviceError

    with pytest.raises(DeviceError) as e:
        open_port(url, 115200)
    assert str(e.value) == (f"cannot open {url}: expected socket://HOST:PORT, PORT a number "
                            "0-65535")
