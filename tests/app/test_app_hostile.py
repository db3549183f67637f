"""difareli-app against hostile requests, over loopback with raw http.client requests: foreign Host and
Origin, wrong body types and lengths, deep JSON, wrong field types and ranges, checkpoint paths outside the served
set (no existence oracle), bounded caches, huge lights, an abandoned relight, a port in use, an imported official
checkpoint beside a store it cannot read."""

from __future__ import annotations

import http.client
import json
import socket
import subprocess
import sys
import time

import pytest

from difareli.app.server import serve_in_thread
from difareli.app.service import Service

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def app(tiny_checkpoint, synth_store):
    svc = Service(checkpoint=str(tiny_checkpoint("difareli_pp")), store=str(synth_store), max_relighters=2,
                  max_sources=2)
    server, url = serve_in_thread(svc)
    yield svc, server.server_port
    server.shutdown()
    server.server_close()


def raw(port: int, method: str, path: str, body: bytes | dict | None = None, timeout: float = 60,
        **headers) -> tuple[int, dict]:
    """One request with exactly the headers given (``Host_``-style names: ``_`` -> ``-``; None drops one)."""
    data = json.dumps(body).encode() if isinstance(body, dict) else (body or b"")
    want = {"Host": f"127.0.0.1:{port}", "Content-Type": "application/json", "Content-Length": str(len(data))}
    if method == "GET":
        del want["Content-Type"], want["Content-Length"]
    want.update({k.replace("_", "-"): v for k, v in headers.items()})
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        for k, v in want.items():
            if v is not None:
                conn.putheader(k, v)
        conn.endheaders(data)
        r = conn.getresponse()
        return r.status, json.loads(r.read() or b"{}")
    finally:
        conn.close()


def _record(app) -> str:
    svc, port = app
    status, src = raw(port, "POST", "/api/source", {"kind": "record", "id": svc.records()[0]})
    assert status == 200, src
    return src["id"]


# ---------------------------------------------------------------------------------------------- headers
def test_foreign_host_is_refused_even_for_reads(app):
    _, port = app
    for host in ("evil.example:%d" % port, f"127.0.0.1:{port + 1}", "attacker.test", "127.0.0.1.nip.io:%d" % port):
        for method, path in (("GET", "/api/info"), ("POST", "/api/relight")):
            status, out = raw(port, method, path, {"id": "x"} if method == "POST" else None, Host=host)
            assert status == 403 and "not this app's address" in out["error"], (host, out)
    assert raw(port, "GET", "/api/info", Host=f"localhost:{port}")[0] == 200


def test_foreign_origin_cannot_post(app):
    _, port = app
    for origin in ("http://evil.example", "null", f"https://127.0.0.1:{port}", f"http://127.0.0.1:{port + 1}"):
        status, out = raw(port, "POST", "/api/relight", {"id": "nope"}, Origin=origin)
        assert status == 403 and "Origin" in out["error"], (origin, out)
    status, out = raw(port, "POST", "/api/relight", {"id": "nope"}, Sec_Fetch_Site="cross-site")
    assert status == 403
    status, out = raw(port, "POST", "/api/relight", {"id": "nope"}, Origin=f"http://127.0.0.1:{port}")
    assert status == 400 and "unknown" in out["error"]  # its own page gets through to the field checks


def test_only_json_bodies(app):
    _, port = app
    for ctype in ("text/plain", "application/x-www-form-urlencoded", "multipart/form-data; boundary=x", None):
        status, out = raw(port, "POST", "/api/relight", {"id": "nope"}, Content_Type=ctype)
        assert status == 415 and "application/json" in out["error"], (ctype, out)


@pytest.mark.parametrize("length,status,words", [("-1", 400, "not a byte count"), ("abc", 400, "not a byte count"),
                                                 ("1e3", 400, "not a byte count"), (None, 411, "missing"),
                                                 (str(10 ** 11), 413, "over the 48 MiB limit")])
def test_content_length_is_bounded_and_checked(app, length, status, words):
    _, port = app
    got, out = raw(port, "POST", "/api/relight", b'{"id": "nope"}', timeout=10, Content_Length=length)
    assert got == status and words in out["error"] and "\n" not in out["error"], out


def test_deep_json_is_refused_not_a_dropped_connection(app):
    _, port = app
    for body in (b"[" * 100_000 + b"]" * 100_000, json.dumps({"id": "x", "light": [[[[[[[[[[1]]]]]]]]]]}).encode()):
        status, out = raw(port, "POST", "/api/relight", body)
        assert status == 400 and "nested too deeply" in out["error"], out
    status, out = raw(port, "POST", "/api/relight", b'{"id": NaN}')
    assert status == 400 and "not JSON" in out["error"]


@pytest.mark.parametrize("change,field", [({"steps": "5"}, "steps="), ({"steps": 2.5}, "steps="),
                                          ({"steps": True}, "steps="), ({"steps": 0}, "steps="),
                                          ({"steps": 10 ** 9}, "steps="), ({"sampler": 3}, "sampler="),
                                          ({"light": "up"}, "light="), ({"shadow": "dark"}, "shadow="),
                                          ({"shadow": -0.5}, "shadow="), ({"shadow": 7}, "shadow="),
                                          ({"light": {"kind": "direction", "direction": ["a", 0, 1]}},
                                           "light.direction[0]="),
                                          ({"light": {"kind": "direction", "direction": [1, 0]}}, "light.direction="),
                                          ({"light": {"kind": "envmap", "name": "studio", "rotation": 1e9}},
                                           "light.rotation="),
                                          ({"light": {"kind": "sun"}}, "light.kind="), ({"id": 5}, "id="),
                                          ({"checkpoint": ["a"]}, "checkpoint="), ({"stepz": 3}, "stepz: unknown")])
def test_wrong_field_types_and_ranges_answer_400_naming_the_field(app, change, field):
    _, port = app
    body = {"id": _record(app), "sampler": "ddim", "steps": 2, "light": {"kind": "direction", "direction": [0, 0, 1]},
            **change}
    status, out = raw(port, "POST", "/api/relight", body)
    assert status == 400 and out["error"].startswith(field) and "\n" not in out["error"], out


def test_huge_light_is_refused_in_terms_of_the_light(app):
    _, port = app
    for d in ([1e154, 0, 0], [1e300, 1e300, 1e300], [-1e200, 0, 1]):
        status, out = raw(port, "POST", "/api/relight", {"id": _record(app), "sampler": "ddim", "steps": 2,
                                                         "light": {"kind": "direction", "direction": d}})
        assert status == 400 and out["error"].startswith("light.direction[0]=") and "|x| <= 1e+06" in out["error"]
    status, out = raw(port, "POST", "/api/relight", {"id": _record(app), "light": {"direction": [0, 0, 0]}})
    assert status == 400 and "no direction" in out["error"]


def test_checkpoint_outside_the_served_set_is_no_existence_oracle(app, tmp_path):
    svc, port = app
    (tmp_path / "exists.ckpt").write_bytes(b"x" * 1234)
    answers = []
    for name in ("exists.ckpt", "missing.ckpt"):
        path = str(tmp_path / name)
        for route, body in (("/api/relight", {"id": _record(app), "checkpoint": path}),
                            ("/api/source", {"kind": "record", "id": svc.records()[0], "checkpoint": path})):
            status, out = raw(port, "POST", route, body)
            assert status == 400 and "is not one this app serves" in out["error"], out
            answers.append(out["error"].replace(name, "NAME"))
    assert len(set(answers)) == 1 and "1234" not in answers[0] and "exist" not in answers[0], answers
    status, out = raw(port, "POST", "/api/relight", {"id": _record(app), "checkpoint": "/etc/passwd"})
    assert status == 400 and "not one this app serves" in out["error"]


# ---------------------------------------------------------------------------------------------- memory
def test_200_steps_values_do_not_grow_the_caches(app):
    svc, port = app
    built = svc.built
    for steps in range(1, 201):  # an unknown source: nothing may be built for it
        status, out = raw(port, "POST", "/api/relight", {"id": "photo-unknown", "sampler": "ddim", "steps": steps})
        assert status == 400 and "unknown" in out["error"]
    assert svc.built == built
    rid = _record(app)
    for steps in (1, 2, 3, 4):  # a real source: every steps value builds one, the cache keeps max_relighters
        status, out = raw(port, "POST", "/api/relight", {"id": rid, "sampler": "ddim", "steps": steps,
                                                         "light": {"kind": "direction", "direction": [1, 0, 1]}})
        assert status == 200, out
        assert len(svc._relighters) <= svc.max_relighters == 2
    for rid in svc.records()[:4]:
        assert raw(port, "POST", "/api/source", {"kind": "record", "id": rid})[0] == 200
    assert len(svc._sources) <= svc.max_sources == 2
    status, out = raw(port, "GET", "/api/info")
    assert out["cache"] == {"relighters": 2, "sources": 2, "inversions": 8}


# ---------------------------------------------------------------------------------------------- an abandoned relight
@pytest.mark.slow  # asserts the next relight answers within 20 s of wall time
def test_abandoned_relight_gives_the_lock_back(app):
    svc, port = app
    rid = _record(app)
    before = svc.cancel.cancelled
    body = json.dumps({"id": rid, "sampler": "ddim", "steps": 1000}).encode()
    s = socket.create_connection(("127.0.0.1", port))
    s.sendall(b"POST /api/relight HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nContent-Type: application/json\r\n"
              b"Content-Length: %d\r\n\r\n%s" % (port, len(body), body))
    time.sleep(1.0)  # the relight has started (1000 inversion steps take far longer)
    s.close()
    t0 = time.perf_counter()
    status, out = raw(port, "POST", "/api/relight", {"id": rid, "sampler": "ddim", "steps": 2})
    assert status == 200, out
    assert svc.cancel.cancelled > before and time.perf_counter() - t0 < 20
    assert not svc.lock.locked()


# ---------------------------------------------------------------------------------------------- start-up
def test_port_in_use_is_one_line_before_the_model_loads():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        r = subprocess.run([sys.executable, "-m", "difareli.cli.app", f"port={port}", "checkpoint=nowhere.ckpt",
                            "warm=false"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"difareli-app: port={port}: cannot listen on 127.0.0.1:{port}")
    assert "nowhere.ckpt" not in r.stderr  # the model was not loaded: the port was checked first


def test_imported_official_checkpoint_beside_a_foreign_store_is_one_line(synth_store, tmp_path):
    from difareli.official.weights import import_checkpoint
    from tests.official.test_official_checkpoint import write_run

    run, cfg, _ = write_run(tmp_path)
    out = tmp_path / "imported.ckpt"
    import_checkpoint(run, cfg, out, verify=False)
    svc = Service(checkpoint=str(out), store=str(synth_store))
    server, _ = serve_in_thread(svc)
    try:
        status, got = raw(server.server_port, "POST", "/api/source", {"kind": "record", "id": svc.records()[0]})
    finally:
        server.shutdown()
        server.server_close()
    assert status == 400 and "\n" not in got["error"] and got["error"].startswith(f"checkpoint={out}"), got
    assert "reads" in got["error"] or "lacks" in got["error"] or "does not fit" in got["error"]
