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

Why the standard library: a framework would add a dependency for little; the checks here are the ones a local
JSON API needs (a WSGI/ASGI framework does not check Host or Origin by default either).
"""

from __future__ import annotations

import json
import select
import socket
import sys
import threading
import traceback
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from . import checks, examples, presets
from .checks import MAX_BODY, Guard, RequestError  # noqa: F401 (MAX_BODY re-exported)
from .service import Service
from difareli.errors import user_message


def error_message(exc: BaseException) -> str | None:
    """The one-line message of a user error (as the CLIs print it after ``difareli-<name>: ``), else None."""
    if isinstance(exc, RequestError):
        return str(exc)
    return user_message(exc)


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


class Handler(BaseHTTPRequestHandler):
    service: Service  # set on the subclass made by make_server
    guard: Guard
    quiet = True
    timeout = 120  # seconds a client may take to send its request (a stalled body must not hold a thread)

    def log_message(self, fmt: str, *args: Any) -> None:  # the default logs every request to stderr
        if not self.quiet:
            super().log_message(fmt, *args)

    def _send(self, status: int, body: bytes, ctype: str) -> None:
        try:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("X-Frame-Options", "DENY")
            self.end_headers()
            self.wfile.write(body)
        except (BrokenPipeError, ConnectionResetError):  # the client left: nobody to answer
            self.close_connection = True

    def _json(self, status: int, obj: Any) -> None:
        self._send(status, json.dumps(obj).encode(), "application/json")

    def _refuse(self, e: RequestError) -> None:
        self.close_connection = True  # an unread or bad body must not be parsed as the next request
        self._json(e.status, {"error": str(e)})

    def do_GET(self) -> None:
        try:
            self.guard.check(self.headers, state_changing=False)
        except RequestError as e:
            return self._refuse(e)
        if self.path in ("/", "/index.html"):
            self._send(200, page(), "text/html; charset=utf-8")
        elif self.path == "/api/info":
            self._guarded(lambda: self.service.info())
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
        try:
            self.guard.check(self.headers, state_changing=True)
            if self.path not in routes:
                raise RequestError(f"{self.path[:200]}: no such endpoint", 404)
            body = checks.parse_body(self.rfile.read(checks.body_length(self.headers)))
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
            msg = error_message(e)
            if msg is None:
                traceback.print_exc(file=sys.stderr)
                self._json(500, {"error": f"internal error: {type(e).__name__}: {e}"})
            else:
                self._json(400, {"error": msg.splitlines()[0] if msg else type(e).__name__})
            return
        self._json(200, out)


def make_server(service: Service | None, host: str = "127.0.0.1", port: int = 8765, quiet: bool = True,
                allowed_hosts: tuple[str, ...] = ()) -> ThreadingHTTPServer:
    """A server for ``service`` bound to ``host:port`` (port 0: any free port; ``server.server_port`` says which);
    ``allowed_hosts``: further names the Host header may carry. A port in use is an OSError (bind). ``service``
    may be None and set later (``server.RequestHandlerClass.service``): the CLI binds before loading a model."""
    handler = type("BoundHandler", (Handler,), {"service": service, "quiet": quiet})
    server = ThreadingHTTPServer((host, port), handler)
    server.daemon_threads = True
    handler.guard = Guard(host, server.server_port, allowed_hosts)
    return server


def serve_in_thread(service: Service, host: str = "127.0.0.1", port: int = 0) -> tuple[ThreadingHTTPServer, str]:
    """Start a server on a background thread (tests, notebooks); returns it and its URL."""
    server = make_server(service, host, port)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://{host}:{server.server_port}/"
