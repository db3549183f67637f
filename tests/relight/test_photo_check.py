"""The check before relighting (issue 44): measures that move the right way and a verdict with its fix."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from difareli.relight import photo, photo_check

pytestmark = pytest.mark.skipif(not all(importlib.util.find_spec(m) for m in ("mediapipe", "dlib")),
                                reason="needs the photo estimators")
ENC = ["image", "shading", "shape", "identity", "light", "normal"]


@pytest.fixture(scope="module")
def astronaut():
    import skimage.data

    return skimage.data.astronaut()


def test_a_good_photo_is_ok_and_a_small_one_is_not(astronaut):
    import cv2

    good = photo_check.check(photo.prepare_photo(astronaut, ENC, size=64), "astronaut")
    assert good.ok, good.line()
    assert 70 < good.measures["face_px"] < 110 and good.measures["past_edge"] == 0
    assert good.line().startswith("astronaut: will relight well")
    small = cv2.resize(astronaut, (160, 160), interpolation=cv2.INTER_AREA)
    bad = photo_check.check(photo.prepare_photo(small, ENC, size=64), "small")
    assert bad.measures["face_px"] < 32 and not bad.ok
    assert "face_px" in bad.line() and "larger photo" in bad.line()


def test_tight_crop_and_far_codes_are_flagged(astronaut):
    tight = np.ascontiguousarray(astronaut[100:240, 150:300])
    prepared = photo.prepare_photo(tight, ENC, size=64)
    res = photo_check.check(prepared, "tight")
    assert res.measures["past_edge"] > 0.35 and any("past_edge" in p for p in res.problems)
    full = photo.prepare_photo(astronaut, ENC, size=64)
    ident = full.arrays["identity"].astype(np.float64)
    stats = {"identity": (ident, np.full_like(ident, 0.01))}  # a store of this face: z = 0
    assert photo_check.measure(full, stats)["code_z"] < 1e-6
    stats = {"identity": (ident + 0.5, np.full_like(ident, 0.01))}
    far = photo_check.check(full, "far", stats)
    assert far.measures["code_z"] > 40 and any("code_z" in p for p in far.problems)
