"""What the app accepts of a request, checked before anything runs: the Host and Origin headers (a web page on
another site must neither drive the app nor, via DNS rebinding, read its answers), the body's type, length and
nesting, and every field's type and range. A refusal is a :class:`RequestError` naming the header or field
(HTTP 4xx), never a traceback.
"""

from __future__ import annotations

import ipaddress
import json
import math
import re
from collections.abc import Iterable, Mapping
from typing import Any
from urllib.parse import urlsplit

from difareli.errors import UserError

MAX_BODY = 48 * 2 ** 20
MAX_DEPTH = 8  # the deepest request the page sends is 3 ({"light": {"direction": [...]}})
MAX_STEPS = 1000  # the schedule's T: more steps than timesteps is not a sampler
MAX_DIRECTION = 1e6  # a direction's length does not matter; beyond this a component is a typo or an attack
_LENGTH = re.compile(r"^[0-9]{1,12}$")


class RequestError(UserError):
    """A request the page should not have sent (a bad header or field, an unknown id): one line, HTTP ``status``."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


# ---------------------------------------------------------------------------------------------- headers
def _split_host(value: str) -> tuple[str, int | None]:
    """``"host:port"`` / ``"[::1]:port"`` -> (host, port or None); a malformed one is a RequestError."""
    try:
        parts = urlsplit(f"//{value}")
        return (parts.hostname or ""), parts.port
    except ValueError:
        raise RequestError(f"Host {value!r} is malformed", 400) from None


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        return False


class Guard:
    """The Host / Origin policy of a server bound to ``bind:port``: loopback names always; the bound address;
    with a wildcard bind (0.0.0.0, ::) any IP literal (the LAN address a user types), never another name, which
    is what DNS rebinding sends; ``extra`` names the user allowed at start-up."""

    def __init__(self, bind: str, port: int, extra: Iterable[str] = ()):
        self.port, self.bind = int(port), bind
        self.names = {"localhost", "127.0.0.1", "::1", bind.strip("[]").lower(), *(h.lower() for h in extra)}
        self.any_ip = bind in ("0.0.0.0", "::", "")

    def _host_ok(self, host: str, port: int | None) -> bool:
        if (port if port is not None else 80) != self.port:
            return False
        return host.lower() in self.names or (self.any_ip and _is_ip(host))

    def check(self, headers: Mapping[str, str], state_changing: bool) -> None:
        """Refuse (403) a foreign Host, and on a state-changing request a foreign or opaque Origin."""
        hosts = headers.get_all("Host") if hasattr(headers, "get_all") else [headers.get("Host")]
        if len(hosts or []) > 1:
            raise RequestError("the request has more than one Host header", 400)
        host = headers.get("Host")
        if not host:
            raise RequestError("the request has no Host header; open the app at the URL it printed", 400)
        if not self._host_ok(*_split_host(host)):
            raise RequestError(f"Host {host!r} is not this app's address (port {self.port}); open the URL it "
                               "printed (start it with allowed_hosts=[<name>] to serve another name)", 403)
        origin = headers.get("Origin")
        if state_changing and (headers.get("Sec-Fetch-Site") or "").lower() == "cross-site":
            raise RequestError("a cross-site request is refused; use the app's own page", 403)
        if state_changing and origin is not None:
            try:
                o = urlsplit(origin)
                ok = o.scheme == "http" and self._host_ok(o.hostname or "", o.port)
            except ValueError:
                ok = False
            if not ok:
                raise RequestError(f"Origin {origin!r} is not this app's page; only its own page may send "
                                   "requests", 403)


def body_length(headers: Mapping[str, str]) -> int:
    """The checked Content-Length of a POST: present, digits only, at most :data:`MAX_BODY`."""
    if headers.get("Transfer-Encoding"):
        raise RequestError("Transfer-Encoding is not accepted; send a body with a Content-Length", 411)
    ctype = (headers.get("Content-Type") or "").split(";", 1)[0].strip().lower()
    if ctype != "application/json":
        raise RequestError(f"Content-Type {ctype or 'none'!r} is refused; send application/json", 415)
    lengths = headers.get_all("Content-Length") if hasattr(headers, "get_all") else None
    if lengths and len({v.strip() for v in lengths}) > 1:  # which one a proxy reads is anyone's guess: smuggling
        raise RequestError(f"the request has {len(lengths)} Content-Length headers with different values "
                           f"({', '.join(repr(v[:20]) for v in lengths[:3])}); send one", 400)
    raw = headers.get("Content-Length")
    if raw is None:
        raise RequestError("Content-Length is missing; send the JSON body with its length", 411)
    if not _LENGTH.match(raw.strip()):
        raise RequestError(f"Content-Length {raw[:40]!r} is not a byte count (digits only)", 400)
    length = int(raw)
    if length > MAX_BODY:
        raise RequestError(f"Content-Length {length} is over the {MAX_BODY >> 20} MiB limit; send a smaller photo",
                           413)
    return length


def parse_body(data: bytes) -> dict:
    """The JSON object of a body: valid UTF-8 JSON, no NaN/Infinity, nested at most :data:`MAX_DEPTH` deep."""
    def constant(name: str):
        raise UserError(f"{name} is not a number JSON allows")

    try:
        obj = json.loads(data or b"{}", parse_constant=constant)
    except RecursionError:
        raise RequestError(f"the JSON body is nested too deeply (limit {MAX_DEPTH} levels)") from None
    except ValueError as e:
        raise RequestError(f"the request is not JSON ({str(e)[:120]})") from None
    stack = [(obj, 1)]
    while stack:  # iterative: the depth check must not itself recurse
        value, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise RequestError(f"the JSON body is nested too deeply (limit {MAX_DEPTH} levels)")
        items = value.values() if isinstance(value, dict) else value if isinstance(value, list) else ()
        stack.extend((v, depth + 1) for v in items)
    if not isinstance(obj, dict):
        raise RequestError(f"the request body is a JSON {type(obj).__name__}, not an object")
    return obj


def upload_name(value: Any) -> None:
    """An upload's ``name`` the app can write as a file's name: not ``.`` or ``..``, no NUL or control character,
    valid UTF-8 (no lone surrogate), at most 255 bytes, no folder path (`/` or `\\`: the page sends a file's own name);
    a string of another kind is the service's to refuse."""
    if not isinstance(value, str):
        return
    base = value.rsplit("/", 1)[-1]
    try:
        size = len(base.encode("utf-8"))
        problem = None
    except UnicodeEncodeError:
        size, problem = 0, "holds a lone surrogate (not UTF-8 text)"
    if problem is None:
        problem = ("names a folder" if base in (".", "..") else
                   "is a path" if "/" in value or "\\" in value else  # the page sends a file's own name
                   "holds a NUL or control character" if any(ord(c) < 32 or ord(c) == 127 for c in value) else
                   f"is {size} bytes long, over a file name's 255" if size > 255 else None)
    if problem:
        raise RequestError(f"name={_show(value)} {problem}, not a photo's file name; give the photo's own name, e.g. "
                           "face.jpg")


# ---------------------------------------------------------------------------------------------- fields
def _show(value: Any) -> str:
    text = json.dumps(value) if isinstance(value, (int, float, str, bool, type(None))) else type(value).__name__
    return text if len(text) <= 60 else text[:57] + "..."


def only(body: Mapping[str, Any], allowed: Iterable[str], where: str = "") -> None:
    """Refuse a field the API does not know (a typo would otherwise be ignored)."""
    extra = sorted(set(body) - set(allowed))
    if extra:
        raise RequestError(f"{where}{extra[0]}: unknown field; known: {', '.join(sorted(allowed))}")


def text(body: Mapping[str, Any], key: str, *, limit: int = 1024, default: Any = ..., where: str = "") -> Any:
    """A string field (``None`` allowed when ``default`` is None)."""
    value = body.get(key, default)
    if value is ...:
        raise RequestError(f"{where}{key} is missing")
    if value is None and default is None:
        return None
    if not isinstance(value, str) or len(value) > limit:
        raise RequestError(f"{where}{key}={_show(value)} is invalid: must be a string of at most {limit} characters")
    return value


def choice(body: Mapping[str, Any], key: str, options: Iterable[str], default: Any = ..., where: str = "") -> str:
    """A string field that is one of ``options``."""
    options = list(options)
    value = body.get(key, default)
    if value is ... or not isinstance(value, str) or value not in options:
        raise RequestError(f"{where}{key}={'missing' if value is ... else _show(value)} is invalid: use one of "
                           f"{', '.join(options)}")
    return value


def number(body: Mapping[str, Any], key: str, lo: float, hi: float, *, default: Any = ..., integer: bool = False,
           where: str = "") -> Any:
    """A finite number field in ``[lo, hi]`` (an integer when ``integer``; never a bool)."""
    value = body.get(key, default)
    if value is None and default is None:
        return None
    kinds = (int,) if integer else (int, float)
    ok = isinstance(value, kinds) and not isinstance(value, bool) and math.isfinite(value) and lo <= value <= hi
    if not ok:
        kind = "an integer" if integer else "a number"
        raise RequestError(f"{where}{key}={'missing' if value is ... else _show(value)} is invalid: must be {kind} "
                           f"in [{lo:g}, {hi:g}]")
    return value


def direction(value: Any, where: str = "light.direction") -> list[float]:
    """A light direction: three finite numbers, each ``|x| <= MAX_DIRECTION``, not all zero; returned scaled to
    unit length without overflow (a plain norm of 1e154-sized components is inf)."""
    if not isinstance(value, list) or len(value) != 3:
        raise RequestError(f"{where}={_show(value) if not isinstance(value, list) else f'a list of {len(value)}'} "
                           "is invalid: must be [x, y, z] (x right, y up, z toward the viewer)")
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > MAX_DIRECTION:
            raise RequestError(f"{where}[{i}]={_show(v)} is invalid: each component must be a number with |x| <= "
                               f"{MAX_DIRECTION:g} (only the direction matters), e.g. [0.5, 0.3, 0.8]")
    scale = max(abs(float(v)) for v in value)
    if scale == 0:
        raise RequestError(f"{where}=[0, 0, 0] has no direction; give a non-zero [x, y, z]")
    d = [float(v) / scale for v in value]  # largest component is +-1: the norm cannot overflow or underflow
    n = math.sqrt(sum(x * x for x in d))
    return [x / n for x in d]
