"""difareli-app: the light math, the JSON API over HTTP, and the page end to end in a headless chromium
(Debian's chromium + chromium-driver through selenium; skipped, with the reason, where they are absent)."""

from __future__ import annotations

import base64
import json
import os
import shutil
import urllib.error
import urllib.request
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.lighting import sh
from difareli.checkpoints import zoo
from difareli.lighting.presets import ENVMAPS, VISIBLE, preset_light
from difareli.app.server import serve_in_thread
from difareli.app.service import Service
from difareli.relight import relighter as relighter_module

from tests.helpers import HAS_ESTIMATORS, compose_train

pytestmark = pytest.mark.usefixtures("one_thread")
SHIPPED = "difareli_pp-synth64" in zoo.available()
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")


def test_envmaps_light_from_their_bright_side():
    own = sh.directional_light([0, 0, 1], 1.0)
    own[0] += 1.0
    studio = preset_light("studio", own)
    assert sh.dominant_direction(studio)[0] < -0.3  # the key light is on the viewer's left (x < 0)
    # scaled to the source's mean irradiance on a face (here the sphere's visible half)
    assert sh.irradiance(studio, VISIBLE).mean() == pytest.approx(sh.irradiance(own, VISIBLE).mean())
    assert sh.dominant_direction(preset_light("overcast", own))[1] > 0.8  # sky above
    assert set(ENVMAPS) == {"sunset", "studio", "overcast", "window"}


# ------------------------------------------------------------------ the API over HTTP
def _post(url: str, path: str, body: dict) -> tuple[int, dict]:
    req = urllib.request.Request(url + path.lstrip("/"), data=json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=300) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def _png(data_url: str) -> np.ndarray:
    return iio.imread(base64.b64decode(data_url.split(",", 1)[1]))


@pytest.fixture(scope="module")
def record_app(tiny_checkpoint, synth_store):
    svc = Service(checkpoint=str(tiny_checkpoint("difareli_pp")), store=str(synth_store))
    server, url = serve_in_thread(svc)
    yield svc, url
    server.shutdown()


def test_api_relights_a_record_with_seconds_and_reconstruction_error(record_app, monkeypatch):
    _, url = record_app
    inversions = []  # counted, not timed: a timed bound fails on a loaded machine
    real_invert = relighter_module.invert_image
    monkeypatch.setattr(relighter_module, "invert_image", lambda *a, **k: inversions.append(1) or real_invert(*a, **k))
    with urllib.request.urlopen(url + "api/info") as r:
        info = json.loads(r.read())
    assert info["records"] and "unipc" in info["samplers"] and "studio" in info["envmaps"]
    rid = info["records"][0]
    status, src = _post(url, "/api/source", {"kind": "record", "id": rid})
    assert status == 200 and src["id"] == f"record-{rid}" and _png(src["crop"]).shape == (32, 32, 3)
    np.testing.assert_allclose(np.linalg.norm(src["direction"]), 1.0, atol=1e-6)
    results, counts = [], []
    for light in ({"kind": "direction", "direction": [0.7, 0.3, 0.6]}, {"kind": "envmap", "name": "sunset",
                                                                       "rotation": 90}):
        status, out = _post(url, "/api/relight", {"id": src["id"], "sampler": "ddim", "steps": 3, "light": light,
                                                  "shadow": 0.5})
        assert status == 200, out
        assert set(out["seconds"]) >= {"invert", "decode", "total"} and out["seconds"]["total"] > 0
        assert (0 <= out["error"]["mse"] < 1 and 0 <= out["error"]["dssim"] <= 1
                and out["error"]["region"] == "face mask")
        results.append(_png(out["image"]).astype(float))
        counts.append(len(inversions))
    assert results[0].shape == (32, 32, 3) and np.abs(results[0] - results[1]).mean() > 0.5  # the light matters
    assert counts[0] <= 1 and counts[1] == counts[0]  # the second relight reuses the first one's inversion


def test_api_errors_are_one_line(record_app):
    _, url = record_app
    status, out = _post(url, "/api/source", {"kind": "record", "id": "no-such-record"})
    assert status == 400 and out["error"].startswith("record=no-such-record: not in the store")
    status, out = _post(url, "/api/relight", {"id": "record-x", "checkpoint": "missing.ckpt"})
    assert status == 400 and out["error"].startswith("checkpoint='missing.ckpt' is not one this app serves")
    status, out = _post(url, "/api/relight", {"id": "nope"})
    assert status == 400 and "unknown" in out["error"] and "\n" not in out["error"]


def test_bad_upload_gives_the_cli_message(record_app, tiny_checkpoint, tmp_path, monkeypatch):
    """The same file through difareli-relight image=... and through the app: the same one-line message."""
    from difareli.cli.relight import run

    _, url = record_app
    (tmp_path / "notes.txt").write_text("not a photo")
    Path(tmp_path / "tiny.png").write_bytes(iio.imwrite("<bytes>", np.zeros((20, 20, 3), np.uint8), extension=".png"))
    monkeypatch.chdir(tmp_path)
    for name in ("notes.txt", "tiny.png"):
        cfg = compose_train(tmp_path / "out", [f"checkpoint={tiny_checkpoint('difareli_pp')}", f"image={name}",
                                               "target.yaw=30", "progress=false"], config_name="relight")
        with pytest.raises(ValueError) as cli:
            run(cfg)
        data = base64.b64encode((tmp_path / name).read_bytes()).decode()
        status, out = _post(url, "/api/source", {"kind": "upload", "name": name, "data": data})
        assert status == 400 and out["error"] == str(cli.value), (out, str(cli.value))


def test_app_cli_refuses_a_missing_checkpoint(tmp_path):
    from hydra import compose, initialize_config_dir

    from difareli.cli.app import build_service
    from difareli.configs import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("app", overrides=["checkpoint=nowhere.ckpt"])
    with pytest.raises(FileNotFoundError, match="checkpoint=nowhere.ckpt does not exist"):
        build_service(cfg)


# ------------------------------------------------------------------ the page in a real headless browser
def _driver(tmp_path):
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium not installed (pip install -e .[dev])")
    from selenium.webdriver.chrome.service import Service as DriverService

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=1200,900", f"--user-data-dir={tmp_path / 'profile'}"):
        opts.add_argument(flag)
    return webdriver.Chrome(service=DriverService(executable_path=CHROMEDRIVER), options=opts)


@pytest.mark.skipif(not (CHROMIUM and CHROMEDRIVER), reason="no chromium + chromedriver: apt-get install -y chromium "
                    "chromium-driver (.ci/run installs them)")
@pytest.mark.skipif(not (HAS_ESTIMATORS and SHIPPED), reason="photo estimators (DIFARELI_PREPROCESS=1) and the "
                    "shipped checkpoint needed to relight a dropped photo")
def test_page_relights_a_dropped_photo_and_shows_a_bad_upload(tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait
    from skimage import data

    photo = tmp_path / "astronaut.png"
    iio.imwrite(photo, data.astronaut())
    (tmp_path / "notes.txt").write_text("not a photo")
    server, url = serve_in_thread(Service(checkpoint="difareli_pp-synth64"))
    driver = _driver(tmp_path)
    try:
        wait = WebDriverWait(driver, 240)
        driver.get(url)
        wait.until(lambda d: d.find_element(By.TAG_NAME, "body").get_attribute("data-ready") == "1")
        steps = driver.find_element(By.ID, "steps")
        steps.clear()
        steps.send_keys("5")
        driver.find_element(By.ID, "file").send_keys(str(photo))
        wait.until(lambda d: d.find_element(By.ID, "relight").is_enabled())
        assert "(512x512)" in driver.find_element(By.ID, "source-info").text
        before = driver.find_element(By.ID, "direction").text
        sphere = driver.find_element(By.ID, "sphere")  # drag the light to the viewer's right, a little up
        ActionChains(driver).move_to_element_with_offset(sphere, 0, 0).click_and_hold() \
            .move_by_offset(30, -15).move_by_offset(25, -10).release().perform()
        assert driver.find_element(By.ID, "direction").text != before
        wait.until(lambda d: d.find_element(By.ID, "seconds").text.strip() != "" or d.find_element(By.ID, "error").text)
        assert driver.find_element(By.ID, "error").text == ""
        seconds, recon = driver.find_element(By.ID, "seconds").text, driver.find_element(By.ID, "recon").text
        assert " s (" in seconds and "unipc, 5 steps" in seconds and "MSE" in recon and "DSSIM" in recon
        result = driver.find_element(By.ID, "result")
        assert driver.execute_script("return [arguments[0].naturalWidth, arguments[0].naturalHeight]",
                                     result) == [512, 512]  # the whole photo, not the 64 px crop
        shot = Path(os.environ.get("DIFARELI_APP_SCREENSHOT", tmp_path / "app.png"))
        driver.save_screenshot(str(shot))
        assert shot.stat().st_size > 10_000
        driver.find_element(By.ID, "file").send_keys(str(tmp_path / "notes.txt"))
        wait.until(lambda d: d.find_element(By.ID, "error").text != "")
        assert driver.find_element(By.ID, "error").text == \
            "image=notes.txt: not an image file (suffix '.txt'); give a JPEG/PNG face photo"
    finally:
        driver.quit()
        server.shutdown()
