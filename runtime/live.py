"""The live page: a read-only HTTP server (standard library only) fed by the serial loop.

``tactile-run --serve HOST:PORT`` and ``tactile-monitor --serve HOST:PORT`` start a
:class:`Live`. The loop hands it what it has through :meth:`Live.feed` (decoder events, labels,
event objects); it never blocks: each viewer has a bounded queue, and what a slow or vanished
viewer cannot take is dropped for it and counted. Endpoints, GET and HEAD only:

* ``/``: the page (``runtime/web/``: plots of every channel, the current label with all class
  probabilities, the link's status), shipped in the package, no CDN;
* ``/events``: Server-Sent Events, one JSON object per message: the objects stdout carries
  (labels, ``gap``/``stall``/``reconnect`` events) plus ``header`` (the device), ``samples``
  (values in units at about :data:`SAMPLE_HZ`), ``status`` (the link's counters, every second)
  and a last ``end``;
* ``/status``: the latest ``status`` object as JSON.

Anything else is 404; other methods are 405. At most ``max_clients`` viewers at a time: the next
one gets 503 and a line saying so. At most ``max_connections`` connections at a time (each has a
thread): the next is answered 503 and closed without one; a connection that sends no request for
``idle_timeout`` s is closed.
"""

from __future__ import annotations

import ipaddress
import json
import queue
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources

from tactile.cli import parse_address  # noqa: F401  (re-exported: the page's address)
from tactile.device.protocol import DeviceInfo, Header, Samples
from tactile.errors import ConfigError
from tactile.runtime.stream import Label
from tactile.runtime.units import to_units

SAMPLE_HZ = 25.0  # samples per second per channel sent to viewers (the plots need no more)
MAX_CLIENTS = 4
MAX_CONNECTIONS = 32  # connections (threads) at a time, viewers included
IDLE_TIMEOUT_S = 10.0  # a connection that sends no request for this long is closed
QUEUE = 512  # messages held per viewer before its new messages are dropped
WRITE_TIMEOUT_S = 10.0  # a viewer that has taken nothing for this long is disconnected
SNDBUF = 64 * 1024  # kernel send buffer per viewer, bytes
STATUS_EVERY_S = 1.0
KEEPALIVE_S = 15.0
_FILES = {"/": ("index.html", "text/html; charset=utf-8"),
          "/app.js": ("app.js", "text/javascript; charset=utf-8"),
          "/style.css": ("style.css", "text/css; charset=utf-8")}
_STICKY = ("header", "label", "change", "status")  # a new viewer gets the latest of each first
_END = b'data: {"event":"end"}\n\n'
_BUSY = (b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n"
         b"Content-Length: 38\r\nRetry-After: 10\r\nConnection: close\r\n\r\n"
         b"busy: too many connections; try later\n")


def link_status(stats) -> dict:
    """The decoder's counters a viewer needs (a :class:`~tactile.device.protocol.DecoderStats`)."""
    return {k: getattr(stats, k) for k in ("bytes_in", "frames", "samples", "crc_errors",
                                           "malformed", "bytes_discarded", "gaps",
                                           "samples_lost", "restarts")}


@dataclass(eq=False)
class _Viewer:
    address: str
    queue: queue.Queue = field(default_factory=lambda: queue.Queue(QUEUE))
    dropped: int = 0
    gone: threading.Event = field(default_factory=threading.Event)


class _Server(ThreadingHTTPServer):
    """One thread per connection, at most ``live.max_connections`` of them: past that, a
    connection gets a fixed 503 and is closed at once, from the listening thread."""

    daemon_threads = True
    live: Live
    connections = 0

    def process_request(self, request, client_address) -> None:
        with self.live._lock:
            busy = self.connections >= self.live.max_connections
            if busy:
                self.live.turned_away += 1
            else:
                self.connections += 1
        if not busy:
            super().process_request(request, client_address)
            return
        try:
            request.setblocking(False)  # a short answer into a fresh socket's empty buffer
            request.send(_BUSY)
        except OSError:
            pass
        self.shutdown_request(request)

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self.live._lock:
                self.connections -= 1

    def handle_error(self, request, client_address) -> None:
        """A viewer that resets, drops or stalls its connection mid-request is its own
        business: the page goes on, and stderr (the command's diagnostics) gets no traceback.
        Anything else (a page file that cannot be read, say) is one line."""
        e = sys.exc_info()[1]
        if isinstance(e, (ConnectionError, TimeoutError)):
            return
        self.live.say(f"live page: a request from {client_address[0]} failed "
                      f"({type(e).__name__}: {e})")


class _Server6(_Server):
    address_family = socket.AF_INET6


class Live:
    """The server and its viewers.

    Args:
        host, port: where to listen (port 0: a free one; :attr:`url` says which).
        status: called once a second (from the server's thread) for the link's counters,
            published as a ``status`` object; keep it to reading numbers.
        say: gets the diagnostics lines (the address, refused viewers).
        max_clients: viewers at a time.
        max_connections: connections at a time (viewers, page loads, idle keep-alives).
        idle_timeout: a connection that sends no request for this long (s) is closed.
        status_every: the ``status`` period, s.
        write_timeout: a viewer that takes nothing for this long (s) is disconnected (its
            browser reconnects by itself when it can).
        labels: whether labels will come (False: ``tactile-monitor``, the page shows no label).
    """

    def __init__(self, host: str, port: int, status: Callable[[], dict],
                 say: Callable[[str], None] = lambda m: print(m, file=sys.stderr, flush=True),
                 max_clients: int = MAX_CLIENTS, write_timeout: float = WRITE_TIMEOUT_S,
                 labels: bool = True, max_connections: int = MAX_CONNECTIONS,
                 idle_timeout: float = IDLE_TIMEOUT_S, status_every: float = STATUS_EVERY_S
                 ) -> None:
        self.status, self.say, self.labels = status, say, labels
        self.max_clients, self.write_timeout = max_clients, write_timeout
        self.max_connections, self.idle_timeout = max_connections, idle_timeout
        self.status_every = status_every
        self._lock = threading.Lock()
        self._viewers: list[_Viewer] = []
        self._latest: dict[str, bytes] = {}
        self._info: DeviceInfo | None = None
        self._every = 1
        self.served = self.refused = self.dropped = self.published = self.turned_away = 0
        self.closing = threading.Event()  # nothing more is published but the last messages
        self.ended = threading.Event()  # `end` is in every viewer's queue (or dropped there)
        try:
            self._server = (_Server6 if ":" in host else _Server)((host, port), _Handler)
        except OSError as e:
            raise ConfigError(f"--serve {host}:{port}: cannot listen there ({e.strerror or e})"
                              ) from None
        self._server.live = self
        bound = self._server.server_address
        self.host, self.port = host, bound[1]
        shown = f"[{host}]" if ":" in host else host
        self.url = f"http://{shown}:{self.port}/"
        self._threads = [threading.Thread(target=self._server.serve_forever, daemon=True),
                         threading.Thread(target=self._status_loop, daemon=True)]
        for t in self._threads:
            t.start()
        self.say(f"live page at {self.url} (read-only; at most {max_clients} viewers)")

    # -- fed by the loop ------------------------------------------------------------------

    def feed(self, item) -> None:
        """Everything from the loop goes through here, and returns at once: a decoder event
        (:class:`~tactile.device.protocol.Header` and :class:`~tactile.device.protocol.Samples`
        become ``header`` and ``samples`` objects; a gap is left to the printer's event), a
        :class:`~tactile.runtime.stream.Label`, or a dict (an event object as on stdout)."""
        if isinstance(item, dict):
            self.publish(item)
        elif isinstance(item, Header):
            self._header(item.info)
        elif isinstance(item, Samples):
            if self._info is not None:
                self._samples(item)
        elif isinstance(item, Label):
            self.publish(item.to_dict())

    def publish(self, obj: dict, _last: bool = False) -> None:
        """Queue ``obj`` for every viewer; a full queue drops it for that viewer (counted)."""
        if self.closing.is_set() and not _last:  # after the end: nothing more
            return
        kind = obj.get("event", "label")
        data = b"data: " + json.dumps(obj, separators=(",", ":")).encode() + b"\n\n"
        with self._lock:
            self.published += 1
            if kind in _STICKY:
                self._latest[kind] = data
            for v in self._viewers:
                try:
                    v.queue.put_nowait(data)
                except queue.Full:
                    v.dropped += 1
                    self.dropped += 1

    def _header(self, info: DeviceInfo) -> None:
        self._info = info
        self._every = max(1, round(info.sample_rate_hz / SAMPLE_HZ))
        self.publish({"event": "header", "device": info.device, "labels": self.labels,
                      "sample_rate_hz": info.sample_rate_hz, "every": self._every,
                      "channels": [{"name": c.name, "unit": c.unit} for c in info.channels]})

    def _samples(self, ev: Samples) -> None:
        first = (-ev.seq) % self._every  # keep the samples whose seq is a multiple of `every`
        if first >= len(ev.raw):
            return
        values = to_units(self._info, ev.raw[first::self._every])
        self.publish({"event": "samples", "seq": ev.seq + first, "every": self._every,
                      "values": [[float(f"{v:.4g}") for v in row] for row in values.tolist()]})

    # -- the server's side ----------------------------------------------------------------

    def _status_loop(self) -> None:
        last = (time.monotonic(), None)
        while not self.closing.wait(self.status_every):
            last = self._publish_status(last)

    def _publish_status(self, last: tuple[float, int | None],
                        _last: bool = False) -> tuple[float, int | None]:
        st = dict(self.status())
        now, samples = time.monotonic(), st.get("samples")
        then, before = last
        st["rate_hz"] = None  # null until a status before this one gives a count to measure by
        if samples is not None and before is not None and now > then:
            st["rate_hz"] = round((samples - before) / (now - then), 1)
        with self._lock:
            st.update(viewers=len(self._viewers), dropped=self.dropped, refused=self.refused)
        self.publish({"event": "status", **st}, _last)
        return now, samples

    def host_allowed(self, host_header: str) -> bool:
        """Bound to loopback, the page answers only to requests that name a loopback host: a
        web page elsewhere cannot read it through a name that resolves to 127.0.0.1 (DNS
        rebinding). Bound to another address, any name (the board's, a phone's view of it)."""
        if not ipaddress.ip_address(self._server.server_address[0]).is_loopback:
            return True
        name = host_header.rsplit(":", 1)[0] if not host_header.endswith("]") else host_header
        return name.strip("[]").lower() in ("localhost", "127.0.0.1", "::1")

    @property
    def viewers(self) -> int:
        with self._lock:
            return len(self._viewers)

    def latest_status(self) -> bytes:
        with self._lock:
            data = self._latest.get("status", b"data: {}\n\n")
        return data[len(b"data: "):].strip() + b"\n"

    def join(self, address: str) -> _Viewer | None:
        """A new viewer, with the latest header, label and status queued first; None when
        there are already ``max_clients``."""
        with self._lock:
            if len(self._viewers) >= self.max_clients or self.closing.is_set():
                self.refused += 1
                return None
            v = _Viewer(address)
            for kind in _STICKY:
                if kind in self._latest:
                    v.queue.put_nowait(self._latest[kind])
            self._viewers.append(v)
            self.served += 1
            return v

    def leave(self, v: _Viewer) -> None:
        with self._lock:
            if v in self._viewers:
                self._viewers.remove(v)
        v.gone.set()

    def close(self, drain_s: float = 2.0) -> None:
        """A last ``status`` and ``end`` to every viewer, up to ``drain_s`` s for them to take
        what is queued (each viewer's thread ends once it has written its last message), then
        stop listening. Says how many viewers were served."""
        self.closing.set()
        self._publish_status((time.monotonic(), None), _last=True)
        self.publish({"event": "end"}, _last=True)
        self.ended.set()
        deadline = time.monotonic() + drain_s
        with self._lock:
            viewers = list(self._viewers)
        for v in viewers:
            v.gone.wait(max(0.0, deadline - time.monotonic()))
        self._server.shutdown()
        self._server.server_close()
        self.say(f"live page: viewers {self.served} served, {self.refused} refused; "
                 f"{self.dropped} messages dropped for slow viewers"
                 + (f"; {self.turned_away} connections turned away (busy)"
                    if self.turned_away else ""))


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"
    server_version = "tactile"

    def version_string(self) -> str:  # the Server header: "tactile" (no Python version)
        return self.server_version

    def setup(self) -> None:
        self.timeout = self.server.live.idle_timeout  # applied to the socket by super()
        super().setup()

    def log_message(self, format, *args) -> None:  # noqa: A002  (quiet: no line per request)
        pass

    def do_GET(self) -> None:  # noqa: N802
        self._answer(body=True)

    def do_HEAD(self) -> None:  # noqa: N802
        self._answer(body=False)

    def _refuse_method(self) -> None:
        self._send(HTTPStatus.METHOD_NOT_ALLOWED, b"read-only: GET and HEAD only\n",
                   "text/plain; charset=utf-8", extra={"Allow": "GET, HEAD"})

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _refuse_method  # noqa: N815

    def _send(self, code: int, data: bytes, ctype: str, body: bool = True,
              extra: dict | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", "default-src 'self'")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if body:
            self.wfile.write(data)

    def _answer(self, body: bool) -> None:
        path = self.path.split("?", 1)[0]
        live = self.server.live
        if not live.host_allowed(self.headers.get("Host", "")):
            self._send(HTTPStatus.FORBIDDEN, b"this page answers to localhost names only\n",
                       "text/plain; charset=utf-8", body)
        elif path in _FILES:
            name, ctype = _FILES[path]
            data = resources.files("tactile.runtime").joinpath("web", name).read_bytes()
            self._send(HTTPStatus.OK, data, ctype, body)
        elif path == "/status":
            self._send(HTTPStatus.OK, live.latest_status(), "application/json", body)
        elif path == "/events":
            self._events(live, body)
        else:
            self._send(HTTPStatus.NOT_FOUND, f"no such page: {path}\n".encode(),
                       "text/plain; charset=utf-8", body)

    def _events(self, live: Live, body: bool) -> None:
        viewer = live.join(self.client_address[0]) if body else None
        if body and viewer is None:
            self._send(HTTPStatus.SERVICE_UNAVAILABLE,
                       f"busy: at most {live.max_clients} viewers at a time; try again later\n"
                       .encode(), "text/plain; charset=utf-8", extra={"Retry-After": "10"})
            return
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        if viewer is None:  # HEAD
            return
        self.close_connection = True
        self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SNDBUF)
        self.connection.settimeout(live.write_timeout)
        idle = 0.0
        try:
            self.wfile.write(b"retry: 2000\n\n")
            while True:
                try:
                    data = viewer.queue.get(timeout=0.25)
                except queue.Empty:
                    if live.ended.is_set():  # and nothing left: `end` was written or dropped
                        return
                    idle += 0.25
                    if idle >= KEEPALIVE_S:  # a comment line: finds a vanished viewer
                        idle = 0.0
                        self.wfile.write(b": keepalive\n\n")
                    continue
                idle = 0.0
                self.wfile.write(data)
                self.wfile.flush()
                if data == _END:
                    return
        except OSError:  # the viewer went away, or took nothing for write_timeout s
            pass
        finally:
            live.leave(viewer)


class Tee:
    """A printer that also hands each label and event to a :class:`Live`."""

    def __init__(self, printer, live: Live) -> None:
        self.printer, self.live = printer, live

    def label(self, lab) -> None:
        self.printer.label(lab)
        self.live.feed(lab)

    def event(self, kind: str, **fields) -> None:
        self.printer.event(kind, **fields)
        self.live.feed({"event": kind, **fields})


def serve_runner(address: str, runner, decoder, say: Callable[[str], None]) -> Live:
    """``tactile-run --serve``: a :class:`Live` fed by ``runner``
    (:class:`~tactile.runtime.runner.Runner`): its printer is teed, its decoder events tapped, and
    the status reads its summary and ``decoder``'s counters."""
    summary = runner.summary

    def status() -> dict:
        return {**link_status(decoder.stats), "windows": summary.windows, "gaps": summary.gaps,
                "reconnects": summary.reconnects, "stalls": summary.stalls}

    live = Live(*parse_address(address), status, say)
    runner.printer = Tee(runner.printer, live)
    runner.tap = live.feed
    return live
