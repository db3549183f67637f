"""The app's local web server: the standard library's ``ThreadingHTTPServer``, one page (``static/index.html``) and
a JSON API over :class:`~difareli.app.service.Service`. Nothing is fetched from outside; it listens on
localhost by default.

    GET  /              the page
    GET  /api/info      checkpoints, samplers, HDR maps, store records
    POST /api/source    {"kind": "upload", "name", "data": <data URL>} | {"kind": "record", "id"}; "checkpoint"
    POST /api/relight   {"id", "checkpoint", "sampler", "steps", "light": {...}, "shadow": 0..1}

Bad input (an upload that is not an image, too small, without a face; an unknown checkpoint) is answered 400 with
``{"error": <the CLI's one-line message>}``; anything else 500 with its type and message (traceback on stderr).
"""

from __future__ import annotations

import json
import sys
import threading
import traceback
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from .service import RequestError, Service, decode_upload

MAX_BODY = 48 * 2 ** 20


def error_message(exc: BaseException) -> str | None:
    """The one-line message of a user error (as the CLIs print it after ``difareli-<name>: ``), else None."""
    from difareli.errors import user_message

    if isinstance(exc, RequestError):
        return str(exc)
    return user_message(exc)


def page() -> bytes:
    return resources.files("difareli.app").joinpath("static/index.html").read_bytes()


class Handler(BaseHTTPRequestHandler):
    service: Service  # set on the subclass made by make_server
    quiet = True

    def log_message(self, fmt: str, *args: Any) -> None:  # the default logs every request to stderr
        if not self.quiet:
            super().log_message(fmt, *args)

    def _send(self, status: int, body: bytes, ctype: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, status: int, obj: Any) -> None:
        self._send(status, json.dumps(obj).encode(), "application/json")

    def do_GET(self) -> None:
        if self.path in ("/", "/index.html"):
            self._send(200, page(), "text/html; charset=utf-8")
        elif self.path == "/api/info":
            self._guarded(lambda: self.service.info())
        elif self.path == "/healthz":
            self._json(200, {"ok": True})
        else:
            self._json(404, {"error": f"{self.path}: no such page"})

    def do_POST(self) -> None:
        length = int(self.headers.get("Content-Length") or 0)
        if length > MAX_BODY:
            self._json(413, {"error": f"request of {length >> 20} MiB is over the {MAX_BODY >> 20} MiB limit"})
            return
        try:
            body = json.loads(self.rfile.read(length) or b"{}")
        except ValueError as e:
            self._json(400, {"error": f"the request is not JSON ({e})"})
            return
        routes = {"/api/source": self._source, "/api/relight": self._relight}
        if self.path not in routes:
            self._json(404, {"error": f"{self.path}: no such endpoint"})
            return
        self._guarded(lambda: routes[self.path](body))

    def _source(self, body: dict) -> dict:
        svc = self.service
        with svc.lock:
            if body.get("kind") == "record":
                s = svc.record(str(body.get("id")), body.get("checkpoint"))
            elif body.get("kind") == "upload":
                s = svc.upload(str(body.get("name") or "upload"), decode_upload(str(body.get("data") or "")),
                               body.get("checkpoint"))
            else:
                raise RequestError("source kind must be 'upload' or 'record'")
            return svc.describe(s)

    def _relight(self, body: dict) -> dict:
        with self.service.lock:
            return self.service.relight(body)

    def _guarded(self, fn) -> None:
        try:
            out = fn()
        except Exception as e:  # noqa: BLE001 - every failure becomes a JSON answer the page can show
            msg = error_message(e)
            if msg is None:
                traceback.print_exc(file=sys.stderr)
                self._json(500, {"error": f"internal error: {type(e).__name__}: {e}"})
            else:
                self._json(400, {"error": msg.splitlines()[0] if msg else type(e).__name__})
            return
        self._json(200, out)


def make_server(service: Service, host: str = "127.0.0.1", port: int = 8765, quiet: bool = True) -> ThreadingHTTPServer:
    """A server for ``service`` bound to ``host:port`` (port 0: any free port; ``server.server_port`` says which)."""
    handler = type("BoundHandler", (Handler,), {"service": service, "quiet": quiet})
    server = ThreadingHTTPServer((host, port), handler)
    server.daemon_threads = True
    return server


def serve_in_thread(service: Service, host: str = "127.0.0.1", port: int = 0) -> tuple[ThreadingHTTPServer, str]:
    """Start a server on a background thread (tests, notebooks); returns it and its URL."""
    server = make_server(service, host, port)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://{host}:{server.server_port}/"
