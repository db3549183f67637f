"""difareli-app's page in a real headless Chromium (Debian's chromium + chromium-driver through selenium, as
tests/app/test_app.py): a real app on a free loopback port, the shipped student checkpoint (one network pass), and
the page clicked like a user: an example photo, a preset light, the gallery of every preset, the before/after
slider and the download link. ``DIFARELI_SCREENSHOTS=docs/images`` also saves the screenshots the docs show
(app_gallery.png, app_before_after.png). Skipped, with the reason, where Chromium, its driver, selenium or the photo
estimators are missing."""

from __future__ import annotations

import base64
import os
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.app.presets import presets
from difareli.app.server import serve_in_thread
from difareli.app.service import Service
from difareli.checkpoints import zoo

from tests.helpers import HAS_ESTIMATORS

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_thread")]
STUDENT = "difareli_pp_ss-synth64"
CHROMIUM = next((p for p in (shutil.which("chromium"), shutil.which("chromium-browser"), "/usr/bin/chromium")
                 if p and os.access(p, os.X_OK)), None)
CHROMEDRIVER = shutil.which("chromedriver")


def _png(data_url: str) -> np.ndarray:
    assert data_url.startswith("data:image/png;base64,"), data_url[:40]
    return iio.imread(base64.b64decode(data_url.split(",", 1)[1]))


@pytest.fixture
def page(tmp_path):
    """A headless Chromium on a fresh app serving the student; yields (driver, wait)."""
    if not CHROMIUM:
        pytest.skip("no Chromium found (chromium / chromium-browser): apt-get install -y chromium chromium-driver")
    if not CHROMEDRIVER:
        pytest.skip("no chromedriver found: apt-get install -y chromium-driver")
    if not (HAS_ESTIMATORS and STUDENT in zoo.available()):
        pytest.skip("photo estimators (DIFARELI_PREPROCESS=1) and the shipped student needed to relight an example")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium not installed (pip install -e .[dev])")
    from selenium.webdriver.chrome.service import Service as DriverService
    from selenium.webdriver.support.ui import WebDriverWait

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=1280,1000", "--hide-scrollbars",
                 f"--user-data-dir={tmp_path / 'profile'}"):
        opts.add_argument(flag)
    server, url = serve_in_thread(Service(checkpoint=STUDENT))  # port 0: a free port
    driver = webdriver.Chrome(service=DriverService(executable_path=CHROMEDRIVER), options=opts)
    try:
        driver.get(url)
        wait = WebDriverWait(driver, 300)
        wait.until(lambda d: d.execute_script("return document.body.dataset.ready") == "1")
        yield driver, wait
    finally:
        driver.quit()
        server.shutdown()
        server.server_close()


def _shot(driver, name: str, tmp_path: Path) -> Path:
    """A screenshot under $DIFARELI_SCREENSHOTS (the docs' images) or tmp_path."""
    folder = Path(os.environ.get("DIFARELI_SCREENSHOTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    driver.save_screenshot(str(folder / name))
    assert (folder / name).stat().st_size > 20_000
    return folder / name


def test_page_examples_presets_gallery_slider_download(page, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    driver, wait = page
    js = driver.execute_script
    by_id = lambda i: driver.find_element(By.ID, i)  # noqa: E731
    assert [b.get_attribute("data-example") for b in by_id("examples").find_elements(By.TAG_NAME, "button")] == \
        ["astronaut", "camera"]
    names = [p["name"] for p in presets()]
    assert [b.get_attribute("data-preset") for b in by_id("presets").find_elements(By.TAG_NAME, "button")] == names

    # The cameraman first: the photo check's verdict (head turned) and the grey-photo note in the notice.
    driver.find_element(By.CSS_SELECTOR, "#examples button[data-example=camera]").click()
    wait.until(lambda d: by_id("relight").is_enabled() or by_id("error").text)
    assert by_id("error").text == "" and by_id("notice").is_displayed()
    notice = by_id("notice").text
    assert "may relight poorly: the head is turned" in notice and "warning: grey photo" in notice

    # The astronaut: a good verdict; the input photo is the "before" of the slider.
    driver.find_element(By.CSS_SELECTOR, "#examples button[data-example=astronaut]").click()
    wait.until(lambda d: "astronaut" in by_id("source-info").text and by_id("relight").is_enabled())
    assert "will relight well" in by_id("notice").text and "(512x512)" in by_id("source-info").text
    assert js("return [document.getElementById('before').naturalWidth, document.getElementById('result').hidden]") \
        == [512, True]

    # A preset: the light is set and the photo relit; the download is the whole composited photo.
    driver.find_element(By.CSS_SELECTOR, "#presets button[data-preset=left]").click()
    wait.until(lambda d: by_id("download").is_displayed() or by_id("error").text)
    assert by_id("error").text == ""
    assert by_id("direction").text.startswith("x -0.9")  # the sphere shows the preset's direction
    link = by_id("download")
    assert link.get_attribute("download") == "relit-astronaut-left.png"
    relit = _png(link.get_attribute("href"))
    assert relit.shape == (512, 512, 3) and link.get_attribute("href") == by_id("result").get_attribute("src")
    assert js("return document.getElementById('result').naturalWidth") == 512

    # The gallery: every preset, one relight after another, each tile labelled with its preset and downloadable.
    by_id("gallery-btn").click()
    wait.until(lambda d: js("return document.body.dataset.gallery") == "done")
    assert by_id("error").text == "" and by_id("gallery-text").text == f"done: {len(names)} lights"
    assert js("return [document.getElementById('gallery-progress').value, "
              "document.getElementById('gallery-progress').max]") == [len(names), len(names)]
    tiles = by_id("gallery").find_elements(By.TAG_NAME, "figure")
    assert [t.get_attribute("data-preset") for t in tiles] == names
    shots = {}
    for t, p in zip(tiles, presets()):
        assert t.find_element(By.TAG_NAME, "figcaption").text.startswith(p["label"])
        a = t.find_element(By.CSS_SELECTOR, "figcaption a")
        assert a.get_attribute("download") == f"relit-astronaut-{p['name']}.png"
        shots[p["name"]] = _png(a.get_attribute("href")).astype(float)
        assert shots[p["name"]].shape == (512, 512, 3)
        assert js("return arguments[0].naturalWidth", t.find_element(By.TAG_NAME, "img")) == 512
    face = (slice(60, 200), slice(150, 260))
    assert np.abs(shots["left"][face] - shots["right"][face]).mean() > 1.0  # the tiles differ where the face is
    assert np.abs(shots["hdr-sunset"][face] - shots["hdr-overcast"][face]).mean() > 0.5
    js("arguments[0].scrollIntoView()", by_id("gallery"))
    _shot(driver, "app_gallery.png", tmp_path)

    # A tile shows its relight in the before/after view; the slider, dragged or set, moves the split.
    tiles[1].find_element(By.TAG_NAME, "img").click()
    assert by_id("download").get_attribute("download") == "relit-astronaut-right.png"
    assert by_id("direction").text.startswith("x 0.9")  # the tile's light is the current light again
    js("arguments[0].scrollIntoView()", by_id("compare"))
    split = lambda: js("return getComputedStyle(document.getElementById('compare')).getPropertyValue('--split')")
    js("const r = document.getElementById('compare-range'); r.value = 30; r.dispatchEvent(new Event('input'))")
    assert split().strip() == "30%"
    assert "30%" in js("return getComputedStyle(document.getElementById('result')).clipPath")
    box = by_id("compare")
    ActionChains(driver).move_to_element_with_offset(box, box.size["width"] // 4, 0).click().perform()
    assert 70 <= float(by_id("compare-range").get_attribute("value")) <= 80  # a click at 3/4 of the width
    ActionChains(driver).move_to_element_with_offset(box, -box.size["width"] // 4, 0).click().perform()
    assert 20 <= float(by_id("compare-range").get_attribute("value")) <= 30
    assert abs(by_id("compare-range").size["width"] - box.size["width"]) <= 2  # the range spans the photo
    js("const r = document.getElementById('compare-range'); r.value = 45; r.dispatchEvent(new Event('input'))")
    js("window.scrollTo(0, 0)")  # the split through the face: the input's half on the left, the relit on the right
    _shot(driver, "app_before_after.png", tmp_path)
