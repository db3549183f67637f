"""difareli-app holds a crowd: requests past the queue bound are answered 503 with Retry-After (never reset
unanswered) and every 200 equals its one-at-a-time answer; silent and trickling clients are cut off and free their
connection slot; two different Content-Length headers, upload names that are no file names, and a weights folder
given at start (listed in /api/info)."""

from __future__ import annotations

import http.client
import json
import shutil
import socket
import threading
import time

import pytest

from difareli.app.server import Limits, serve_in_thread
from difareli.app.service import Service
from difareli.checkpoints import zoo

pytestmark = pytest.mark.usefixtures("one_thread")
LIGHTS = [[x, y, 1.0] for x in (-0.6, 0.6) for y in (-0.5, 0.0, 0.3, 0.5)]  # 8 distinct directions


@pytest.fixture(scope="module")
def crowd(tiny_checkpoint, synth_store):
    svc = Service(checkpoint=str(tiny_checkpoint("difareli_pp")), store=str(synth_store))
    server, _ = serve_in_thread(svc, limits=Limits(queue=2, connections=16, read_timeout=5.0))
    yield svc, server
    server.shutdown()
    server.server_close()


def request(port: int, method: str, path: str, body: dict | None = None) -> tuple[int, dict, dict]:
    """(status, headers, JSON answer) of one request."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
    try:
        data = json.dumps(body).encode() if body is not None else None
        conn.request(method, path, body=data, headers={"Content-Type": "application/json"} if data else {})
        r = conn.getresponse()
        return r.status, dict(r.getheaders()), json.loads(r.read() or b"{}")
    finally:
        conn.close()


def read_all(s: socket.socket) -> bytes:
    """Everything the server sends until it closes the connection (HTTP/1.0: after its answer)."""
    chunks = []
    while chunk := s.recv(65536):
        chunks.append(chunk)
    return b"".join(chunks)


def _relight(rid: str, light: list[float]) -> dict:
    return {"id": rid, "sampler": "ddim", "steps": 2, "light": {"kind": "direction", "direction": light}}


def _same(answer: dict) -> dict:
    return {k: v for k, v in answer.items() if k != "seconds"}  # everything but the timings


def test_past_the_queue_bound_503_with_retry_after_and_every_200_equals_its_lone_answer(crowd):
    svc, server = crowd
    port = server.server_port
    status, _, src = request(port, "POST", "/api/source", {"kind": "record", "id": svc.records()[0]})
    assert status == 200, src
    request(port, "POST", "/api/relight", _relight(src["id"], [0, 0, 1]))  # the reconstruction is cached now
    alone = [request(port, "POST", "/api/relight", _relight(src["id"], d)) for d in LIGHTS]
    assert all(s == 200 for s, _, _ in alone)
    results: dict[int, tuple] = {}

    def fire(i: int) -> None:
        results[i] = request(port, "POST", "/api/relight", _relight(src["id"], LIGHTS[i]))

    svc.lock.acquire()  # the relight running: the first two wait for it, the other six are past the bound
    try:
        threads = [threading.Thread(target=fire, args=(i,)) for i in range(len(LIGHTS))]
        for t in threads:
            t.start()
        deadline = time.monotonic() + 60
        while (len(results) < 6 or server.admitted < 2) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(results) == 6 and server.admitted == 2
    finally:
        svc.lock.release()
    for t in threads:
        t.join(120)
    statuses = sorted(s for s, _, _ in results.values())
    assert statuses == [200, 200] + [503] * 6
    for i, (status, headers, out) in results.items():
        if status == 503:
            assert int(headers["Retry-After"]) >= 1 and out["error"].startswith("the app is busy: 2 requests are "
                                                                                "queued, its bound; retry in")
        else:
            assert _same(out) == _same(alone[i][2]), i  # the same images and error as when it ran alone
    # A handler leaves the count after its answer is written, so the client may read the answer first.
    deadline = time.monotonic() + 5
    while server.admitted and time.monotonic() < deadline:
        time.sleep(0.01)
    assert server.admitted == 0


def test_silent_and_trickling_clients_are_cut_off_and_free_their_slot(crowd):
    svc, _ = crowd
    server, _ = serve_in_thread(svc, limits=Limits(queue=1, connections=2, read_timeout=1.0))
    port = server.server_port
    try:
        silent = socket.create_connection(("127.0.0.1", port))
        trickle = socket.create_connection(("127.0.0.1", port))
        trickle.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1:%d\r\n" % port)
        t0 = time.monotonic()
        for _ in range(3):  # a header byte now and then, never the blank line
            trickle.sendall(b"X")
            time.sleep(0.2)
        # Both slots are held: this request waits in the backlog until the reaper frees one, then is answered.
        status, _, out = request(port, "GET", "/healthz")
        waited = time.monotonic() - t0
        assert status == 200 and out == {"ok": True} and 0.5 < waited < 10, waited
        trickle.settimeout(10)
        answer = read_all(trickle)
        assert answer.startswith(b"HTTP/1.0 408 ") and b"took over 1 s to arrive" in answer
        silent.settimeout(10)
        assert read_all(silent) == b""  # no request line: closed without an answer
    finally:
        server.shutdown()
        server.server_close()


def test_two_different_content_lengths_are_refused(crowd):
    _, server = crowd
    body = b'{"id": "nope"}'
    s = socket.create_connection(("127.0.0.1", server.server_port), timeout=30)
    s.sendall(b"POST /api/relight HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nContent-Type: application/json\r\n"
              b"Content-Length: %d\r\nContent-Length: 5\r\n\r\n%s" % (server.server_port, len(body), body))
    answer = read_all(s).decode()
    s.close()
    assert answer.startswith("HTTP/1.0 400 ")
    assert ('"the request has 2 Content-Length headers with different values (\'14\', \'5\'); send one"'
            in answer), answer


@pytest.mark.parametrize("name,problem", [("..", "names a folder"), ("x/..", "names a folder"),
                                          ("a\x00b.png", "holds a NUL or control character"),
                                          ("\ud800.png", "holds a lone surrogate (not UTF-8 text)"),
                                          ("é" * 200 + ".png", "is 404 bytes long, over a file name's 255"),
                                          ("../../etc/passwd", "is a path"), ("C:\\me\\face.png", "is a path")])
def test_upload_names_that_are_no_file_names_are_one_line(crowd, name, problem):
    _, server = crowd
    status, _, out = request(server.server_port, "POST", "/api/source",
                             {"kind": "upload", "name": name, "data": "data:image/png;base64,iVBORw0KGgo="})
    assert status == 400 and problem in out["error"] and out["error"].startswith("name=")
    assert "\n" not in out["error"] and "/tmp" not in out["error"] and "Traceback" not in out["error"]


def test_a_weights_folder_given_at_start_is_listed(tmp_path):
    folder = tmp_path / "w"
    shutil.copytree(zoo.SHIPPED_DIR / "difareli_pp_ss-synth64", folder)
    shutil.copytree(folder, tmp_path / "runs" / "nested" / "w2")
    svc = Service(checkpoint="difareli_pp_ss-synth64", checkpoints=(str(folder), str(tmp_path / "runs")))
    server, _ = serve_in_thread(svc)
    try:
        status, _, out = request(server.server_port, "GET", "/api/info")
    finally:
        server.shutdown()
        server.server_close()
    assert status == 200
    assert str(folder) in out["checkpoints"] and str(tmp_path / "runs" / "nested" / "w2") in out["checkpoints"]
    assert svc.allowed_checkpoint(str(folder)) == str(folder)  # and a request may name it


def test_server_limits_are_checked_before_the_port_is_bound():
    from hydra import compose, initialize_config_dir

    from difareli.cli.app import limits
    from difareli.configs import CONFIG_DIR
    from difareli.errors import UserError

    def cfg(*overrides):
        with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
            return compose("app", overrides=list(overrides))

    assert limits(cfg()) == Limits(8, 64, 128, 20.0)  # conf/app.yaml's bounds are the documented ones
    for bad, words in (("server.queue=0", "server.queue=0 is invalid"),
                       ("server.connections=8", "server.connections=8 is not above server.queue=8"),
                       ("server.read_timeout=0", "server.read_timeout=0 is invalid"),
                       ("server.backlog=100000", "server.backlog=100000 is invalid")):
        with pytest.raises(UserError, match=words):
            limits(cfg(bad))


def test_an_upload_is_read_by_its_bytes_not_its_name(monkeypatch):
    """Before (issue 64, our probe): a PNG sent with no name (the API's default "upload") or named IMG_0001 was
    refused "image=upload: not an image file (suffix 'none')"; empty or non-base64 data was called an unreadable
    image ("%%%%" decoded to no bytes); ../../etc/passwd was answered "image=passwd: not an image file"."""
    from difareli.app.examples import example_png
    from difareli.app.service import decode_upload
    from difareli.errors import UserError
    from difareli.app.checks import RequestError

    svc = Service(checkpoint="difareli_pp_ss-synth64")
    seen = []
    monkeypatch.setattr(svc, "photo", lambda name, rgb, ckpt, notes=(): seen.append((name, rgb.shape)))
    for name in ("upload", "IMG_0001", "face.PNG", "face.jpg"):
        svc.upload(name, example_png("astronaut"))
    assert seen == [(n, (512, 512, 3)) for n in ("upload", "IMG_0001", "face.PNG", "face.jpg")]
    with pytest.raises(UserError) as e:
        svc.upload("notes", b"hello")
    assert str(e.value) == ("image=notes: unreadable image (UnidentifiedImageError: cannot identify image file "
                            "'notes'); give a JPEG/PNG face photo")
    for data, words in (("", "the upload is empty (no data); send the photo's bytes as a data: URL or base64"),
                        ("data:image/png;base64,", "the upload is empty"),
                        ("%%%%", "the upload is not base64 data (")):
        with pytest.raises(RequestError) as e:
            decode_upload(data)
        assert str(e.value).startswith(words), str(e.value)
    assert decode_upload("data:image/png;base64,aGVs\nbG8=") == b"hello"  # line breaks are not data


def test_a_full_disk_on_the_server_is_507_without_its_paths(crowd, monkeypatch):
    """Before (issue 64, our probe: an upload while the server's temporary folder is full): 400 "no space left on the
    device writing /tmp/tmpXXXX/face.png (...); free space or give another output folder", the server's scratch path
    and a fix for the operator given to the client as the client's fault."""
    import errno
    from pathlib import Path

    _, server = crowd
    real = Path.write_bytes

    def full(self, data):
        if self.name == "face.png":
            raise OSError(errno.ENOSPC, "No space left on device", str(self))
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", full)
    status, _, out = request(server.server_port, "POST", "/api/source",
                             {"kind": "upload", "name": "face.png", "data": "data:image/png;base64,iVBORw0KGgo="})
    assert status == 507, (status, out)
    assert out["error"] == ("the app's server ran out of disk space; this is not your request: retry once its "
                            "operator has fixed it (the app's console names the file)")
