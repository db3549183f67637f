"""The check before relighting: measures that move the right way, a verdict with its fix, and the rule that
calibrates its limits (scripts/calibrate_photo_check.py)."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.relight import photo, photo_check

from tests.helpers import HAS_ESTIMATORS

needs_estimators = pytest.mark.skipif(not HAS_ESTIMATORS, reason="needs the photo estimators")
ENC = ["image", "shading", "shape", "identity", "light", "normal"]


@pytest.fixture(scope="module")
def astronaut():
    import skimage.data

    return skimage.data.astronaut()


@needs_estimators
def test_a_good_photo_is_ok_and_a_small_one_is_not(astronaut):
    import cv2

    good = photo_check.check(photo.prepare_photo(astronaut, ENC, size=64), "astronaut")
    assert good.ok, good.line()
    assert 70 < good.measures["face_px"] < 110 and good.measures["past_edge"] == 0
    assert good.line().startswith("astronaut: will relight well")
    limit = photo_check.LIMITS["face_px"][0]
    side = round(512 * 0.75 * limit / good.measures["face_px"])  # the face at 3/4 of the limit
    small = cv2.resize(astronaut, (side, side), interpolation=cv2.INTER_AREA)
    bad = photo_check.check(photo.prepare_photo(small, ENC, size=64), "small")
    assert bad.measures["face_px"] < limit and not bad.ok
    assert f"the face is {bad.measures['face_px']:.0f} px wide, under 28 px" in bad.line()
    assert "larger photo" in bad.line()


@needs_estimators
def test_tight_crop_and_far_codes_are_flagged(astronaut):
    tight = np.ascontiguousarray(astronaut[100:240, 150:300])
    prepared = photo.prepare_photo(tight, ENC, size=64)
    res = photo_check.check(prepared, "tight")
    assert res.measures["past_edge"] > photo_check.LIMITS["past_edge"][0]
    assert any("of the face's square lies outside the photo" in p for p in res.problems)
    assert res.measures["face_outside"] > photo_check.LIMITS["face_outside"][0]
    assert "will relight well" not in res.line()
    full = photo.prepare_photo(astronaut, ENC, size=64)
    ident = full.arrays["identity"].astype(np.float64)
    stats = {"identity": (ident, np.full_like(ident, 0.01))}  # a store of this face: z = 0
    assert photo_check.measure(full, stats)["code_z"] < 1e-6
    stats = {"identity": (ident + 0.5, np.full_like(ident, 0.01))}
    far = photo_check.check(full, "far", stats)
    assert far.measures["code_z"] > 40 and any("standard deviations from the training faces" in p for p in far.problems)


JARGON = ("face_px", "yaw_deg", "pitch_deg", "landmark_px", "light_rel_rmse", "past_edge", "face_outside", "code_z")


@needs_estimators
def test_a_tight_crop_whose_face_runs_past_the_edge_is_not_called_good_and_the_line_is_plain(astronaut):
    from skimage.transform import resize

    # The astronaut's face box (x 178-273, y 83-178) widened to 140 px and made a 112 px chip, as in issue 61: its
    # face's square lies 37% past the edge, under that limit, and 14% of the face itself lies past it.
    chip = resize(astronaut[60:200, 155:295], (112, 112), anti_aliasing=True, preserve_range=True).astype(np.uint8)
    res = photo_check.check(photo.prepare_photo(chip, ENC, size=64), "chip")
    assert res.measures["past_edge"] < photo_check.LIMITS["past_edge"][0]
    assert res.measures["face_outside"] > photo_check.LIMITS["face_outside"][0]
    assert res.line().startswith("chip: may relight poorly: ") and "of the face lies outside the photo" in res.line()
    good = photo_check.check(photo.prepare_photo(astronaut, ENC, size=64), "astronaut")
    assert good.measures["face_outside"] == 0
    for line in (res.line(), good.line()):
        assert not any(j in line for j in JARGON), line


def test_choose_limit_is_where_the_final_run_of_worse_bins_begins():
    values = np.arange(40.0)
    dssim = np.where(values < 20, 0.1, 0.3)
    # Bins of 8 from the good end; the third (16..23) holds 4 good and 4 bad photos: median 0.2 > 0.1 + 0.05.
    assert photo_check.choose_limit(values, dssim, 0.1, margin=0.05, bin_size=8) == 15.5
    # Lower is worse (face_px): bad below 20, sorted 39..0, the third bin (23..16) again the first over.
    low = np.where(values < 20, 0.3, 0.1)
    assert photo_check.choose_limit(values, low, 0.1, margin=0.05, worse="lower", bin_size=8) == 23.5
    # One noisy bad bin among good ones is not a limit: the run must reach the worst bin.
    noisy = dssim.copy()
    noisy[:8] = 0.3
    assert photo_check.choose_limit(values, noisy, 0.1, margin=0.05, bin_size=8) == 15.5
    # Nothing worse, or everything worse: no limit within the data.
    assert photo_check.choose_limit(values, np.full(40, 0.1), 0.1, margin=0.05) is None
    assert photo_check.choose_limit(values, np.full(40, 0.3), 0.1, margin=0.05) is None
