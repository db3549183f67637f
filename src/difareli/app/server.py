"""The app's local web server: the standard library's ``ThreadingHTTPServer``, one page (``static/index.html``) and
a JSON API over :class:`~difareli.app.service.Service`. Nothing is fetched from outside; it listens on
127.0.0.1 by default.

    GET  /              the page
    GET  /api/info      checkpoints, samplers, HDR maps, store records, cache sizes
    GET  /api/examples  the example photos (:mod:`~difareli.app.examples`): name, description, size, thumbnail
    GET  /api/presets   the preset lights (:mod:`~difareli.app.presets`), each with the light /api/relight takes
    POST /api/source    {"kind": "upload", "name", "data": <data URL>} | {"kind": "record", "id"} |
                        {"kind": "example", "name"}; "checkpoint". The answer: the crop, the whole input photo,
                        the photo check's verdict and the warnings (``Service.source_answer``)
    POST /api/relight   {"id", "checkpoint", "sampler", "steps", "light": {...}, "shadow": 0..1}

No request is trusted (:mod:`difareli.app.checks`): a Host that is not the app's address is refused 403 (DNS
rebinding), so is a POST whose Origin is another site; a POST must be ``application/json`` with a valid
Content-Length; every field is checked. Bad input is answered 4xx with ``{"error": <one line naming the field>}``
(an upload's error is the CLI's own message); anything else 500 with its type and message (traceback on stderr).
A client that closes its connection while its relight waits or runs cancels it (the lock is given back).

A crowd is held to stated bounds (:class:`Limits`, ``server`` in ``conf/app.yaml``): the kernel's listen backlog
holds ``backlog`` connections not yet accepted; at most ``connections`` are open at once (one thread each; more wait
in the backlog until one closes); at most ``queue`` relight / source requests are held at once (one runs, the rest
wait for the service's lock), and one past the bound is answered 503 with ``Retry-After`` (the seconds a queued
request has taken lately) after its body is drained, never reset unanswered. A client has ``read_timeout`` seconds
to send its whole request (a silent or trickling one is cut off: 408, or closed before its request line), so slow
connections cannot hold the threads. Why the standard library's server: docs/robustness.md.
"""

from __future__ import annotations

import json
import math
import select
import socket
import sys
import threading
import time
import traceback
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from . import checks, examples, presets
from .checks import MAX_BODY, Guard, RequestError  # noqa: F401 (MAX_BODY re-exported)
from .service import Service
from difareli.errors import UserError, is_no_space, user_message


def page() -> bytes:
    return resources.files("difareli.app").joinpath("static/index.html").read_bytes()


def client_gone(sock: socket.socket) -> bool:
    """Whether the peer closed ``sock`` (readable with nothing to read); bytes waiting mean it is still there."""
    try:
        readable, _, _ = select.select([sock], [], [], 0)
        if not readable:
            return False
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False
    except (OSError, ValueError):  # reset, or closed on our side
        return True


@dataclass(frozen=True)
class Limits:
    """How much of a crowd the server holds (module doc); ``conf/app.yaml``'s ``server`` block."""

    queue: int = 8
    connections: int = 64
    backlog: int = 128
    read_timeout: float = 20.0


class AppServer(ThreadingHTTPServer):
    """``ThreadingHTTPServer`` held to :class:`Limits`: a connection slot per open connection (taken before
    ``accept``, so the ones past the cap wait in the listen backlog), a deadline for each request to arrive (a
    reaper cuts off the late ones), and the count of relight / source requests admitted."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], handler: type, limits: Limits):
        self.limits = limits
        self.request_queue_size = limits.backlog  # listen()'s backlog (the standard library's is 5)
        self._slots = threading.BoundedSemaphore(limits.connections)
        self._lock = threading.Lock()
        self._deadlines: dict[socket.socket, float] = {}
        self._late: set[socket.socket] = set()
        self.admitted = 0  # relight / source requests running or waiting for the service's lock
        self.durations: deque[float] = deque(maxlen=8)  # seconds of recent admitted requests (Retry-After)
        super().__init__(address, handler)

    def get_request(self):
        # No free slot: raise (serve_forever polls again) and leave the connection in the kernel's backlog.
        if not self._slots.acquire(timeout=0.2):
            raise OSError("every connection slot is busy")
        try:
            sock, addr = super().get_request()
        except BaseException:
            self._slots.release()
            raise
        with self._lock:
            self._deadlines[sock] = time.monotonic() + self.limits.read_timeout
        return sock, addr

    def shutdown_request(self, request) -> None:  # once per accepted connection, however it ended
        with self._lock:
            self._deadlines.pop(request, None)
            self._late.discard(request)
        try:
            super().shutdown_request(request)
        finally:
            self._slots.release()

    def arrived(self, sock: socket.socket) -> bool:
        """Mark ``sock``'s request as read (no deadline any more); False when the reaper cut it off first."""
        with self._lock:
            self._deadlines.pop(sock, None)
            return sock not in self._late

    def _reap(self, stop: threading.Event) -> None:
        """Cut off connections whose request has not arrived by its deadline (their reads see the end)."""
        while not stop.wait(0.25):
            now = time.monotonic()
            with self._lock:
                late = [s for s, t in self._deadlines.items() if t < now]
                for s in late:
                    del self._deadlines[s]
                    self._late.add(s)
            for s in late:
                try:
                    s.shutdown(socket.SHUT_RD)
                except OSError:  # already closed by its client
                    pass

    def serve_forever(self, poll_interval: float = 0.5) -> None:
        stop = threading.Event()
        threading.Thread(target=self._reap, args=(stop,), daemon=True, name="difareli-app-reaper").start()
        try:
            super().serve_forever(poll_interval)
        finally:
            stop.set()

    @contextmanager
    def admit(self):
        """Yield whether a relight / source request fits within ``limits.queue``; an admitted one is counted
        until it ends (and its seconds kept for Retry-After)."""
        with self._lock:
            ok = self.admitted < self.limits.queue
            self.admitted += ok
        t0 = time.monotonic()
        try:
            yield ok
        finally:
            if ok:
                with self._lock:
                    self.admitted -= 1
                    self.durations.append(time.monotonic() - t0)

    def retry_after(self) -> int:
        """Seconds until a queued slot is likely free: the mean of recent admitted requests, at least 1."""
        with self._lock:
            recent = list(self.durations)
        return max(1, math.ceil(sum(recent) / len(recent))) if recent else 1


class Handler(BaseHTTPRequestHandler):
    service: Service  # set on the subclass made by make_server
    guard: Guard
    server: AppServer
    quiet = True
    timeout = Limits.read_timeout  # per read or write; the whole request also has a deadline (AppServer)

    def log_message(self, fmt: str, *args: Any) -> None:  # the default logs every request to stderr
        if not self.quiet:
            super().log_message(fmt, *args)

    def _send(self, status: int, body: bytes, ctype: str, headers: dict[str, str] | None = None) -> None:
        try:
            self.send_response(status)
            for k, v in (headers or {}).items():
                self.send_header(k, v)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("X-Frame-Options", "DENY")
            self.end_headers()
            self.wfile.write(body)
        except (BrokenPipeError, ConnectionResetError):  # the client left: nobody to answer
            self.close_connection = True

    def _json(self, status: int, obj: Any, headers: dict[str, str] | None = None) -> None:
        self._send(status, json.dumps(obj).encode(), "application/json", headers)

    def _refuse(self, e: RequestError) -> None:
        self.close_connection = True  # an unread or bad body must not be parsed as the next request
        self._json(e.status, {"error": str(e)})

    def _late(self) -> RequestError:
        return RequestError(f"the request took over {self.server.limits.read_timeout:g} s to arrive; send it whole "
                            "at once", 408)

    def _busy(self, length: int) -> None:
        """503 past the queue bound, after draining the body (an unread one would reset the connection)."""
        left = length
        while left > 0:
            chunk = self.rfile.read(min(left, 1 << 16))
            if not chunk:
                break
            left -= len(chunk)
        wait = self.server.retry_after()
        self.close_connection = True
        self._json(503, {"error": f"the app is busy: {self.server.limits.queue} requests are queued, its bound; "
                                  f"retry in {wait} s"}, {"Retry-After": str(wait)})

    def do_GET(self) -> None:
        try:
            if not self.server.arrived(self.connection):
                raise self._late()
            self.guard.check(self.headers, state_changing=False)
        except RequestError as e:
            return self._refuse(e)
        if self.path in ("/", "/index.html"):
            self._send(200, page(), "text/html; charset=utf-8")
        elif self.path == "/api/info":
            self._guarded(self.service.info)
        elif self.path == "/api/examples":
            self._guarded(lambda: {"examples": examples.listing()})
        elif self.path == "/api/presets":
            self._guarded(lambda: {"presets": presets.presets()})
        elif self.path == "/healthz":
            self._json(200, {"ok": True})
        else:
            self._json(404, {"error": f"{self.path[:200]}: no such page"})

    def do_POST(self) -> None:
        routes = {"/api/source": self.service.source_answer, "/api/relight": self.service.relight}
        with self.server.admit() as admitted:
            try:
                self.guard.check(self.headers, state_changing=True)
                if self.path not in routes:
                    raise RequestError(f"{self.path[:200]}: no such endpoint", 404)
                length = checks.body_length(self.headers)
                if not admitted:  # past the bound: its body is drained, never held in memory
                    return self._busy(length)
                data = self.rfile.read(length)
                if not self.server.arrived(self.connection):
                    raise self._late()
                if len(data) < length:
                    raise RequestError(f"the body ended after {len(data)} of its {length} bytes (Content-Length); "
                                       "send it whole")
                body = checks.parse_body(data)
                if self.path == "/api/source" and body.get("kind") == "upload":
                    checks.upload_name(body.get("name"))
            except RequestError as e:
                return self._refuse(e)

            def run() -> dict:
                with self.service.session(lambda: client_gone(self.connection)):
                    return routes[self.path](body)

            self._guarded(run)

    def _guarded(self, fn) -> None:
        try:
            out = fn()
        except RequestError as e:
            self._json(e.status, {"error": str(e).splitlines()[0]})
            return
        except Exception as e:  # noqa: BLE001 - every failure becomes a JSON answer the page can show
            if isinstance(e, OSError) and not isinstance(e, UserError):  # the server's own disk or files: its paths
                return self._server_fault(e)  # and fix are for the operator, not in a 400 to the client
            msg = user_message(e)  # a user error's line, as the CLIs print it; else None
            if msg is None:
                traceback.print_exc(file=sys.stderr)
                self._json(500, {"error": f"internal error: {type(e).__name__}: {e}"})
            else:
                self._json(400, {"error": msg.splitlines()[0] if msg else type(e).__name__})
            return
        self._json(200, out)

    def _server_fault(self, e: OSError) -> None:
        """A full disk (507) or another failing file of the server's own (500), e.g. an upload's scratch copy:
        answered without the server's paths (it was a 400 naming /tmp/<scratch>/<name> and "give another output
        folder"); the whole line goes to the app's stderr."""
        print(f"difareli-app: {user_message(e) or f'{type(e).__name__}: {e}'}", file=sys.stderr)
        full = is_no_space(e)
        why = ("ran out of disk space" if full else
               f"could not read or write a file of its own ({e.strerror or type(e).__name__})")
        self._json(507 if full else 500, {"error": f"the app's server {why}; this is not your request: retry once "
                                                   "its operator has fixed it (the app's console names the file)"})


def make_server(service: Service | None, host: str = "127.0.0.1", port: int = 8765, quiet: bool = True,
                allowed_hosts: tuple[str, ...] = (), limits: Limits | None = None) -> AppServer:
    """A server for ``service`` bound to ``host:port`` (port 0: any free port; ``server.server_port`` says which);
    ``allowed_hosts``: further names the Host header may carry; ``limits``: the crowd it holds (:class:`Limits`).
    A port in use is an OSError (bind). ``service`` may be None and set later
    (``server.RequestHandlerClass.service``): the CLI binds before loading a model."""
    limits = limits or Limits()
    handler = type("BoundHandler", (Handler,), {"service": service, "quiet": quiet, "timeout": limits.read_timeout})
    server = AppServer((host, port), handler, limits)
    handler.guard = Guard(host, server.server_port, allowed_hosts)
    return server


def serve_in_thread(service: Service, host: str = "127.0.0.1", port: int = 0,
                    limits: Limits | None = None) -> tuple[AppServer, str]:
    """Start a server on a background thread (tests, notebooks); returns it and its URL."""
    server = make_server(service, host, port, limits=limits)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://{host}:{server.server_port}/"
