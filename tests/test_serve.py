"""The live page's server (runtime/live.py): endpoints, what /events carries, viewers that do
not read, and tactile-run's labels on stdout while one such viewer is attached."""

from __future__ import annotations

import http.client
import json
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import types

import numpy as np
import pytest
from conftest import REPO, page_url, pen_stream

from tactile.device.protocol import Header, Samples, pen_info
from tactile.errors import ConfigError
from tactile.postprocess.smoothing import PostProcessor, SmoothingSettings
from tactile.runtime.live import QUEUE, Live, parse_address
from tactile.runtime.stream import Label

MODEL = REPO / "models" / "pen-exp2.onnx"


@pytest.fixture
def live():
    said: list[str] = []
    server = Live("127.0.0.1", 0, status=lambda: {"frames": 7}, say=said.append,
                  max_clients=2, status_every=3600)  # a status only when closing
    server.said = said
    yield server
    if not server.closing.is_set():
        server.close(drain_s=0.5)


def get(live: Live, path: str, method: str = "GET") -> tuple[int, dict, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", live.port, timeout=10)
    conn.request(method, path)
    r = conn.getresponse()
    body = r.read()
    conn.close()
    return r.status, dict(r.getheaders()), body


class Viewer:
    """An /events reader: the messages one by one, as dicts."""

    def __init__(self, live: Live) -> None:
        self.sock = socket.create_connection(("127.0.0.1", live.port), timeout=10)
        self.sock.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        self.file = self.sock.makefile("rb")
        self.status_line = self.file.readline().decode()
        while self.file.readline() not in (b"\r\n", b""):  # the headers
            pass

    def next(self) -> dict:
        while True:
            line = self.file.readline()
            if not line:
                raise EOFError("the server closed the stream")
            if line.startswith(b"data: "):
                return json.loads(line[6:])

    def close(self) -> None:
        self.file.close()
        self.sock.close()


def wait_for(cond, what: str, limit: float = 30.0) -> None:
    """Poll ``cond()`` until true (the limit only turns a hang into a failure)."""
    end = time.monotonic() + limit
    while not cond():
        if time.monotonic() > end:
            pytest.fail(f"never happened: {what}")
        time.sleep(0.01)


def test_addresses_bind_to_loopback_unless_told():
    assert parse_address("8000") == ("127.0.0.1", 8000)
    assert parse_address("0.0.0.0:0") == ("0.0.0.0", 0)
    assert parse_address("[::1]:9000") == ("::1", 9000)
    for bad in ("", "x", "host:", ":80", "1.2.3.4:70000", "h:-1"):
        with pytest.raises(ConfigError, match="--serve"):
            parse_address(bad)


@pytest.mark.parametrize("prog", ["tactile-run", "tactile-monitor"])
def test_a_bad_serve_address_is_a_usage_error_before_anything_loads(prog, tmp_path):
    """Was checked after the model loaded (tactile-run: an info line, then the error)."""
    import subprocess
    import sys

    module = {"tactile-run": "run", "tactile-monitor": "monitor"}[prog]
    args = ["--port", "loop://", "--serve", "1.2.3.4:70000"]
    if prog == "tactile-run":  # a model that does not exist: the address is refused first
        args += ["--model", str(tmp_path / "none.onnx")]
    proc = subprocess.run([sys.executable, "-m", f"tactile.runtime.commands.{module}", *args],
                          capture_output=True, text=True, timeout=60)
    assert (proc.returncode, proc.stdout) == (1, ""), proc.stderr
    assert proc.stderr == (f"{prog}: error: argument --serve: '1.2.3.4:70000': expected "
                           "HOST:PORT or PORT (0-65535), e.g. 127.0.0.1:8000 (see --help)\n")


def test_port_0_picks_a_free_port_and_says_where(live):
    assert live.port != 0 and live.url == f"http://127.0.0.1:{live.port}/"
    assert live.said == [f"live page at {live.url} (read-only; at most 2 viewers)"]
    with pytest.raises(ConfigError, match=f"127.0.0.1:{live.port}: cannot listen there"):
        Live("127.0.0.1", live.port, status=dict, say=lambda m: None)  # taken


def test_endpoints_are_read_only_and_unknown_paths_404(live):
    status, headers, body = get(live, "/")
    assert status == 200 and headers["Content-Type"].startswith("text/html")
    assert b'src="app.js"' in body and b"http" not in body.split(b"<footer>")[0]  # no CDN
    for path, kind in (("/app.js", "text/javascript"), ("/style.css", "text/css")):
        status, headers, body = get(live, path)
        assert status == 200 and headers["Content-Type"].startswith(kind) and body
    status, headers, body = get(live, "/", "HEAD")
    assert status == 200 and body == b"" and int(headers["Content-Length"]) > 0
    assert get(live, "/events", "HEAD")[0] == 200 and live.served == 0  # HEAD joins nobody
    assert get(live, "/nothing")[0:3:2] == (404, b"no such page: /nothing\n")
    assert get(live, "/../etc/passwd")[0] == 404
    conn = http.client.HTTPConnection("127.0.0.1", live.port, timeout=10)
    conn.request("GET", "/", headers={"Host": f"evil.example:{live.port}"})  # DNS rebinding
    assert conn.getresponse().status == 403
    conn.close()
    for method in ("POST", "PUT", "DELETE", "PATCH"):
        status, headers, body = get(live, "/", method)
        assert (status, headers["Allow"]) == (405, "GET, HEAD"), method


def test_events_carry_header_samples_labels_and_events_and_a_new_viewer_catches_up(live):
    info = pen_info()
    raw = np.arange(8 * 10, dtype=np.int16).reshape(10, 8) * 100  # seq 6..15
    lab = Label(15, 150_000, "paper", 0.75, {"paper": 0.75, "desk": 0.25}, 0.5)
    first = Viewer(live)
    assert first.status_line.startswith("HTTP/1.1 200")
    live.feed(Header(info))
    live.feed(Samples(6, 60_000, raw))
    live.feed(lab)
    live.feed({"event": "gap", "seq": 16, "missing": 2, "reason": "drop"})
    header = first.next()
    assert header["event"] == "header" and header["every"] == 4  # 100 Hz -> 25 Hz
    assert [c["name"] for c in header["channels"]] == list(info.channel_names)
    samples = first.next()
    # the samples whose seq is a multiple of 4 (8 and 12), in units: counts * scale by hand
    scale = np.array([0.01, 0.01, 1 / 16384, 1 / 16384, 1 / 16384, 1 / 131, 1 / 131, 1 / 131])
    assert samples["seq"] == 8 and samples["every"] == 4
    np.testing.assert_allclose(samples["values"], raw[[2, 6]] * scale, rtol=1e-3)
    assert first.next() == lab.to_dict()  # the object stdout carries, as is
    assert first.next() == {"event": "gap", "seq": 16, "missing": 2, "reason": "drop"}
    late = Viewer(live)  # gets the latest header and label first
    got = [late.next(), late.next()]
    assert got[0]["event"] == "header" and got[1] == lab.to_dict()
    first.close()
    late.close()


def test_events_carry_the_post_processed_label_and_the_changes_as_stdout_does(live):
    """A label with the post-processor's result is the object stdout carries (the raw fields,
    ``smoothed``, ``stable``, ``reset``), a change event as it is; a late viewer gets the
    latest label with its smoothed fields."""
    post = PostProcessor(SmoothingSettings(n=2, p_min=0.6, hold=1), ("paper", "desk"))
    post.reset("gap")
    sm = post.update(np.array([0.75, 0.25]), 0.15, 15)
    lab = Label(15, 150_000, "paper", 0.75, {"paper": 0.75, "desk": 0.25}, 0.5, sm)
    change = {"event": "change", "from": None, "to": "paper", "t": 0.15, "seq": 15}
    v = Viewer(live)
    wait_for(lambda: live.viewers == 1, "the viewer joined")
    live.feed(lab)
    live.feed(change)
    got = v.next()
    assert got == lab.to_dict()
    assert got["smoothed"] == {"label": "paper", "p": 0.75} and got["stable"] is True
    assert got["reset"] == "gap"
    assert v.next() == change
    late = Viewer(live)
    assert late.next() == lab.to_dict()
    v.close()
    late.close()


def test_tactile_run_sends_the_page_what_it_prints(reap):
    """tactile-run post-processing a pen's labels (a socket the test feeds, with a gap): the
    page's /events carries the same label objects, gaps and change events as stdout."""
    pen = socket.create_server(("127.0.0.1", 0))
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.runtime.commands.run", "--model", str(MODEL),
         "--port", f"socket://127.0.0.1:{pen.getsockname()[1]}", "--serve", "127.0.0.1:0",
         "--status-every", "1000", "--stall-timeout", "600", "--smooth", "3", "--p-min", "0.7",
         "--hold", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), 180)
    conn, _ = pen.accept()
    url = page_url(proc.stderr)
    port = int(url.rsplit(":", 1)[1].strip("/"))

    viewer = Viewer(types.SimpleNamespace(port=port))  # all Viewer needs of a Live
    seen: list[dict] = []

    def read() -> None:
        while (m := viewer.next()).get("event") != "end":
            seen.append(m)

    def viewers() -> int:
        c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        c.request("GET", "/status")
        body = c.getresponse().read()
        c.close()
        return json.loads(body).get("viewers", 0)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    n = 3000
    data, spans, _ = pen_stream(n, per_frame=10, seed=3)
    start, end, first, _ = next(s for s in spans if s[2] == 1500 and s[3])  # one frame lost
    wait_for(lambda: viewers() == 1, "the viewer joined", 60)  # before the first label
    conn.sendall(data[:start] + data[end:])
    after = first + 10  # the first sample after the gap; windows of 50 every 25 from there
    last = after + 49 + 25 * ((n - 1 - after - 49) // 25)
    printed = []
    while not printed or printed[-1].get("seq") != last or "label" not in printed[-1]:
        line = proc.stdout.readline()
        assert line, "stdout ended early"
        printed.append(json.loads(line))
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    printed += [json.loads(ln) for ln in out.splitlines()]
    reader.join(30)
    assert not reader.is_alive()
    viewer.close()
    conn.close()
    pen.close()
    assert "0 messages dropped" in err
    page = [m for m in seen if m.get("event") not in ("header", "samples", "status")]
    assert page == [o for o in printed if o.get("event") != "stall"]
    assert any(o.get("reset") == "gap" for o in page) and any(
        o.get("event") == "change" for o in page)
    assert all("smoothed" in o and "stable" in o for o in page if "label" in o)


def test_at_most_max_clients_the_next_is_refused_politely(live):
    viewers = [Viewer(live), Viewer(live)]
    wait_for(lambda: live.viewers == 2, "two viewers joined")
    status, headers, body = get(live, "/events")
    assert status == 503 and body == b"busy: at most 2 viewers at a time; try again later\n"
    assert live.refused == 1
    for v in viewers:
        v.close()


def test_close_sends_end_after_everything_queued(live):
    v = Viewer(live)
    wait_for(lambda: live.viewers == 1, "the viewer joined")
    for i in range(100):
        live.feed({"event": "gap", "seq": i, "missing": 1, "reason": "drop"})
    live.close(drain_s=10)
    got = [v.next() for _ in range(102)]
    assert [g["seq"] for g in got[:100]] == list(range(100))
    assert got[100]["event"] == "status" and got[100]["frames"] == 7
    assert got[101] == {"event": "end"}
    assert live.said[-1] == "live page: viewers 1 served, 0 refused; 0 messages dropped for " \
                            "slow viewers"
    v.close()


def test_the_first_status_has_its_rate_null_not_left_out():
    """A status names every field the page lists; the first had no rate_hz (nothing before it
    to measure the sample rate by)."""
    live = Live("127.0.0.1", 0, status=lambda: {"frames": 0, "samples": 0},
                say=lambda m: None, status_every=3600)  # no status but the one published here
    try:
        live._publish_status((time.monotonic(), None))
        code, headers, body = get(live, "/status")
        status = json.loads(body)
        assert status["event"] == "status" and "rate_hz" in status and status["rate_hz"] is None
        assert headers["Server"] == "tactile"  # no trailing space, no Python version
    finally:
        live.close(drain_s=1)


def test_status_comes_every_period_with_the_servers_counters():
    n = iter(range(10**6))
    live = Live("127.0.0.1", 0, status=lambda: {"frames": 7, "samples": next(n)},
                say=lambda m: None, status_every=0.05)
    v = Viewer(live)
    wait_for(lambda: live.viewers == 1, "the viewer joined")
    got = [v.next() for _ in range(3)]
    assert [g["event"] for g in got] == ["status"] * 3
    assert all(g["frames"] == 7 and g["dropped"] == 0 and g["refused"] == 0 for g in got)
    assert got[-1]["viewers"] == 1 and got[-1]["rate_hz"] > 0  # samples went up each call
    status = json.loads(get(live, "/status")[2])
    assert status["event"] == "status" and status["frames"] == 7

    live.close(drain_s=5)
    while (m := v.next())["event"] != "end":
        assert m["event"] == "status"
    v.close()


def test_a_viewer_idle_while_close_begins_still_gets_the_end(live):
    """close() marks the server closing before it queues the last status and end: a viewer
    whose wait for a message ends in between must not leave without its end."""
    v = Viewer(live)
    wait_for(lambda: live.viewers == 1, "the viewer joined")
    live.closing.set()  # what close() does first; its viewer's 0.25 s waits time out meanwhile
    time.sleep(1.0)  # gives the viewer's thread time to (wrongly) leave; passing needs none
    live.close(drain_s=10)
    assert v.next()["event"] == "status" and v.next() == {"event": "end"}
    v.close()


def test_idle_connections_time_out_and_connections_are_capped():
    said: list[str] = []
    live = Live("127.0.0.1", 0, status=dict, say=said.append, max_connections=3,
                idle_timeout=0.5, status_every=3600)
    idle = [socket.create_connection(("127.0.0.1", live.port), timeout=60) for _ in range(3)]
    wait_for(lambda: live._server.connections == 3, "three connections held")
    extra = socket.create_connection(("127.0.0.1", live.port), timeout=60)
    answer = extra.makefile("rb").read()  # answered at once and closed, no thread
    assert answer.startswith(b"HTTP/1.1 503 ") and answer.endswith(b"busy: too many "
                                                                   b"connections; try later\n")
    assert live.turned_away == 1
    for s in idle:  # none sends a request: each is closed by the server after idle_timeout
        assert s.recv(1) == b""  # (blocks at most the socket's 60 s, then fails the test)
        s.close()
    wait_for(lambda: live._server.connections == 0, "the idle connections' threads ended")
    assert get(live, "/status")[0] == 200  # room again
    live.close(drain_s=0.5)
    assert said[-1].endswith("; 1 connections turned away (busy)")


def stuck_viewer(port: int) -> socket.socket:
    """A viewer that asks for /events and never reads (a small receive buffer fills first)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect(("127.0.0.1", port))
    s.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    return s


def test_a_viewer_that_never_reads_costs_drops_not_waits():
    live = Live("127.0.0.1", 0, status=dict, say=lambda m: None, write_timeout=600,
                status_every=3600)
    stuck = stuck_viewer(live.port)
    wait_for(lambda: live.viewers == 1, "the stuck viewer joined")
    n, payload = 5000, "x" * 1000  # 5 MB: far more than the socket buffers and the queue

    def publish_all() -> None:
        for i in range(n):
            live.publish({"event": "note", "i": i, "pad": payload})

    loop = threading.Thread(target=publish_all, daemon=True)
    loop.start()
    loop.join(60)  # if publish waited for the viewer, the loop would never end
    assert not loop.is_alive() and live.published == n
    # what is not dropped sits in the queue or the socket buffers (<= 64 KiB * 2 + 4 KiB * 2)
    assert n - QUEUE - (2 * 65536 + 2 * 4096) // 1000 <= live.dropped < n
    stuck.close()
    live.close(drain_s=0.5)


def test_tactile_run_labels_go_on_while_a_viewer_never_reads(reap):
    """The pen (a socket the test feeds) sends 600 s of samples while a viewer that never
    reads is attached: stdout still gets every window's label, and the server counts drops."""
    pen = socket.create_server(("127.0.0.1", 0))
    proc = reap(subprocess.Popen(
        [sys.executable, "-m", "tactile.runtime.commands.run", "--model", str(MODEL),
         "--port", f"socket://127.0.0.1:{pen.getsockname()[1]}", "--serve", "127.0.0.1:0",
         "--status-every", "1000"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), 180)
    conn, _ = pen.accept()
    url = page_url(proc.stderr)
    port = int(url.rsplit(":", 1)[1].strip("/"))
    stuck = stuck_viewer(port)

    def viewers() -> int:
        c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        c.request("GET", "/status")
        body = c.getresponse().read()
        c.close()
        return json.loads(body).get("viewers", 0)

    wait_for(lambda: viewers() == 1, "the stuck viewer joined", 60)
    n = 60_000
    data, _, _ = pen_stream(n, seed=3)
    conn.sendall(data)
    from tactile.runtime.model import Model

    c = Model(MODEL).contract
    want = list(range(c.window - 1, n, c.hop))  # the seq of every window's last sample
    seqs = []
    while len(seqs) < len(want):
        line = proc.stdout.readline()
        assert line, "stdout ended early"
        obj = json.loads(line)
        if "label" in obj:
            seqs.append(obj["seq"])
    assert seqs == want
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0
    dropped = int(re.search(r"live page: viewers 1 served.*; (\d+) messages dropped", err)[1])
    assert dropped > 0
    stuck.close()
    conn.close()
    pen.close()


def test_tactile_run_closes_the_page_when_the_port_fails(capsys):
    """A port error ends tactile-run with exit 2: the page still gets its end, and stderr its
    last 'live page:' line."""
    from tactile.runtime.commands import run

    code = run.main(["--model", str(MODEL), "--port", "/dev/tactile-no-such-port",
                     "--serve", "127.0.0.1:0"])
    err = capsys.readouterr().err
    assert code == 2 and "/dev/tactile-no-such-port" in err
    lines = err.splitlines()
    assert any(ln.startswith("tactile-run: live page at http://127.0.0.1:") for ln in lines)
    assert "tactile-run: live page: viewers 0 served, 0 refused; 0 messages dropped for slow " \
           "viewers" in lines


def test_a_viewer_that_resets_its_connection_gets_no_traceback_on_stderr(live, capsys):
    """A client that sends a request and resets the connection (SO_LINGER 0) made
    socketserver print a traceback on the command's stderr, once per connection."""
    import struct

    for _ in range(5):
        s = socket.create_connection(("127.0.0.1", live.port), timeout=10)
        s.sendall(b"GET /app.js HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.close()  # a reset, not a FIN
    wait_for(lambda: live._server.connections == 0, "the handlers to finish")
    assert get(live, "/")[0] == 200  # the page goes on
    # whether a reset lands while the handler reads or writes depends on timing; the handler
    # for both is the server's, called here as socketserver calls it, inside the except
    try:
        raise ConnectionResetError(104, "Connection reset by peer")
    except ConnectionResetError:
        live._server.handle_error(None, ("127.0.0.1", 5))
    for e in (ValueError("bad"), FileNotFoundError(2, "No such file", "app.js")):
        try:
            raise e
        except Exception:
            live._server.handle_error(None, ("127.0.0.1", 6))
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Exception occurred" not in err, err
    assert live.said[-2:] == [
        "live page: a request from 127.0.0.1 failed (ValueError: bad)",
        "live page: a request from 127.0.0.1 failed (FileNotFoundError: [Errno 2] No such "
        "file: 'app.js')"]
