"""difareli-app's page controls (example photos, preset lights, gallery, before/after, download, the photo check's
notice) and the endpoints behind them, over loopback: /api/examples, /api/presets and POST /api/source with
``{"kind": "example"}``, hostile requests included. The page driven in a real browser: tests/app/test_browser.py."""

from __future__ import annotations

import base64
from types import SimpleNamespace
import re
from importlib import resources

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.lighting.presets import ENVMAPS
from difareli.app.examples import EXAMPLES, THUMB
from difareli.app.presets import presets
from difareli.lighting.presets import DIRECTIONS
from difareli.app.server import serve_in_thread
from difareli.app.service import Service
from difareli.checkpoints import zoo
from difareli.lighting import sh

from tests.app.test_app_hostile import raw
from tests.helpers import HAS_ESTIMATORS

pytestmark = pytest.mark.usefixtures("one_thread")
STUDENT = "difareli_pp_ss-synth64"  # one network pass: a relight takes a fraction of a second


def _png(data_url: str) -> np.ndarray:
    assert data_url.startswith("data:image/png;base64,")
    return iio.imread(base64.b64decode(data_url.split(",", 1)[1]))


@pytest.fixture(scope="module")
def app():
    svc = Service(checkpoint=STUDENT)  # nothing is loaded until a source needs the model
    server, _ = serve_in_thread(svc)
    yield svc, server.server_port
    server.shutdown()
    server.server_close()


def test_page_has_the_new_controls():
    html = resources.files("difareli.app").joinpath("static/index.html").read_text()
    ids = set(re.findall(r'id="([^"]+)"', html))
    assert {"examples", "presets", "gallery-btn", "gallery-progress", "gallery", "compare", "before", "result",
            "compare-range", "download", "notice"} <= ids
    assert "<a id=\"download\" download=" in html  # a real download link, not a new tab
    for call in ('"/api/examples"', '"/api/presets"', 'kind: "example"', "relightRequest(p.light)"):
        assert call in html, call
    assert "src=\"http" not in html and "src=\"//" not in html  # nothing fetched from outside
    assert len(html.splitlines()) < 400


def test_examples_endpoint_lists_the_shipped_photos(app):
    _, port = app
    status, out = raw(port, "GET", "/api/examples")
    assert status == 200
    assert [e["name"] for e in out["examples"]] == list(EXAMPLES) == ["astronaut", "camera"]
    for e in out["examples"]:
        thumb = _png(e["thumbnail"])
        assert max(thumb.shape[:2]) == THUMB and (e["width"], e["height"]) == (512, 512) and e["about"]
    colour, grey = (_png(e["thumbnail"]) for e in out["examples"])
    assert colour.ndim == 3 and grey.ndim == 2  # the astronaut in colour, the cameraman grey, as skimage ships them


def test_presets_endpoint_serves_each_light_once(app):
    _, port = app
    status, out = raw(port, "GET", "/api/presets")
    assert status == 200 and out["presets"] == presets()
    names = [p["name"] for p in out["presets"]]
    assert names == ["left", "right", "top", "rim", "front", *(f"hdr-{m}" for m in ENVMAPS)]
    own = sh.directional_light([0.0, 0.0, 1.0], 1.0)
    own[0] += 1.0
    arrays = {"light": own}
    svc = Service(checkpoint=STUDENT)
    source = SimpleNamespace(arrays=arrays, what="a face")
    got = {p["name"]: sh.dominant_direction(svc.target(p["light"]).for_source(None, source)[0].lights[0])
           for p in out["presets"]}
    assert got["left"][0] < -0.8 and got["right"][0] > 0.8  # x: the image's right
    assert got["top"][1] > 0.9 and got["rim"][2] < -0.9 and got["front"][2] > 0.99
    for name, (direction, _) in DIRECTIONS.items():
        np.testing.assert_allclose(got[name], np.asarray(direction) / np.linalg.norm(direction), atol=1e-6)
    assert got["hdr-overcast"][1] > 0.8  # an HDR preset is the same map the envmap control gives


@pytest.mark.parametrize("body, start", [
    ({"kind": "example", "name": "../../etc/passwd"}, 'name="../../etc/passwd" is invalid: use one of astronaut, '
                                                      "camera"),
    ({"kind": "example", "name": "/etc/passwd"}, 'name="/etc/passwd" is invalid'),
    ({"kind": "example", "name": "astronaut.png"}, 'name="astronaut.png" is invalid'),
    ({"kind": "example", "name": ["astronaut"]}, "name=list is invalid"),
    ({"kind": "example"}, "name=missing is invalid"),
    ({"kind": "example", "name": "astronaut", "path": "/etc/passwd"}, "path: unknown field; known: checkpoint, kind, "
                                                                       "name"),
    ({"kind": "example", "name": "astronaut", "checkpoint": "/etc/passwd"}, "checkpoint='/etc/passwd' is not one "
                                                                            "this app serves"),
    ({"kind": "file", "name": "astronaut"}, 'kind="file" is invalid: use one of upload, record, example'),
])
def test_a_hostile_example_request_is_refused_naming_the_field(app, body, start):
    svc, port = app
    status, out = raw(port, "POST", "/api/source", body)
    assert status == 400 and out["error"].startswith(start), out
    assert "\n" not in out["error"] and "root:" not in out["error"]  # one line; no file was read
    assert svc.built == 0  # refused before any model was loaded


def test_new_endpoints_keep_the_host_and_origin_checks(app):
    _, port = app
    for path in ("/api/examples", "/api/presets"):
        status, out = raw(port, "GET", path, Host="evil.example:80")
        assert status == 403 and out["error"].startswith("Host 'evil.example:80' is not this app's address")
    status, out = raw(port, "POST", "/api/source", {"kind": "example", "name": "astronaut"},
                      Origin="http://evil.example")
    assert status == 403 and "Origin" in out["error"]
    status, out = raw(port, "POST", "/api/source", b"kind=example&name=astronaut",
                      Content_Type="application/x-www-form-urlencoded")
    assert status == 415 and "Content-Type" in out["error"]


@pytest.mark.skipif(not (HAS_ESTIMATORS and STUDENT in zoo.available()), reason="photo estimators "
                    "(DIFARELI_PREPROCESS=1) and the shipped student checkpoint needed to prepare an example photo")
def test_an_example_photo_is_a_source_with_its_photo_check_and_relights_whole(app):
    svc, port = app
    status, cam = raw(port, "POST", "/api/source", {"kind": "example", "name": "camera"}, timeout=300)
    assert status == 200, cam
    assert cam["what"] == "image=camera.png" and (cam["width"], cam["height"]) == (512, 512)
    photo = _png(cam["photo"])
    assert photo.shape[:2] == (512, 512) and _png(cam["crop"]).shape == (64, 64, 3)
    # The cameraman's head is turned ~45 degrees: the verdict says so, and the grey photo's note is a warning.
    assert cam["check"]["ok"] is False and any(p.startswith("the head is turned") for p in cam["check"]["problems"])
    assert cam["check"]["line"].startswith("image=camera.png: may relight poorly")
    assert any("grey photo" in w for w in cam["warnings"])
    status, ast = raw(port, "POST", "/api/source", {"kind": "example", "name": "astronaut"}, timeout=300)
    assert status == 200 and ast["check"]["ok"] is True and "will relight well" in ast["check"]["line"]
    again = raw(port, "POST", "/api/source", {"kind": "example", "name": "astronaut"})[1]
    assert again["id"] == ast["id"] and again["preprocess_s"] == 0.0  # prepared once, like an upload
    images = {}
    for p in presets()[:2]:  # left, right
        status, out = raw(port, "POST", "/api/relight", {"id": ast["id"], "light": p["light"]}, timeout=300)
        assert status == 200, out
        images[p["name"]] = _png(out["image"]).astype(float)
        assert images[p["name"]].shape == (512, 512, 3) and _png(out["crop"]).shape == (64, 64, 3)
    assert np.abs(images["left"] - images["right"]).mean() > 0.1  # the light moved
    whole = _png(ast["photo"]).astype(float)
    assert np.abs(images["left"] - whole)[300:].mean() < 1.0  # the face is relit, the suit below it is the photo
    assert np.abs(images["left"] - whole)[60:200, 150:260].mean() > 1.0  # ... and the face is not
