"""The artefact scores on constructed images whose values are known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from difareli.errors import UserError
from difareli.evaluation import artefacts as art
from difareli.lighting import sh

EPS = art.EPS


def grey(value, shape=(64, 64)) -> np.ndarray:
    """A grey uint8 image: its luminance is value / 255 (the Rec. 709 weights sum to 1)."""
    return np.full((*shape, 3), value, np.uint8)


def disc(shape=(64, 64), radius=18) -> np.ndarray:
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    return (yy - shape[0] / 2) ** 2 + (xx - shape[1] / 2) ** 2 < radius ** 2


def test_seam_is_the_log_step_at_the_paste_boundary():
    photo, paste = grey(100), disc()
    pasted = np.where(paste[..., None], grey(200), photo)
    expected = math.log((200 / 255 + EPS) / (100 / 255 + EPS))
    assert art.seam_score(pasted, photo, paste, width=3) == pytest.approx(expected, rel=1e-12)
    assert art.seam_score(photo, photo, paste) == 0.0


def test_seam_ignores_a_change_of_light_that_crosses_the_boundary_smoothly():
    # The whole image twice as bright (a ground truth brightens the background too): r is 0.69 on both sides.
    assert art.seam_score(grey(200), grey(100), disc()) == pytest.approx(0.0, abs=1e-12)


def test_seam_without_an_outside_is_undefined_and_bad_sizes_are_one_line():
    photo = grey(100)
    assert math.isnan(art.seam_score(grey(150), photo, np.ones((64, 64), bool)))
    with pytest.raises(UserError, match="paste region"):
        art.seam_score(photo, photo, np.ones((8, 8), bool))


def checker(shape=(64, 64)) -> np.ndarray:
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    return (yy + xx) % 2 == 0


def test_blotch_scores_a_fine_pattern_at_its_amplitude_and_a_smooth_change_near_zero():
    photo, face = grey(100), disc(radius=28)
    image = np.where(checker()[..., None], grey(120), grey(83))
    hi, lo = (math.log((v / 255 + EPS) / (100 / 255 + EPS)) for v in (120, 83))
    assert art.blotch_score(image, photo, face, sigma=2.0) == pytest.approx((hi - lo) / 2, rel=0.02)
    ramp = np.repeat(np.repeat((100 + np.arange(64))[None, :, None], 64, 0), 3, 2).astype(np.uint8)
    assert art.blotch_score(ramp, photo, face, sigma=2.0) < 1e-3


def test_blotch_leaves_out_the_excluded_pixels():
    photo, face = grey(100), disc(radius=28)
    left = np.zeros((64, 64), bool)
    left[:, :32] = True
    image = np.where((checker() & left)[..., None], grey(120), photo)
    assert art.blotch_score(image, photo, face, sigma=2.0) > 0.05
    exclude = np.zeros((64, 64), bool)
    exclude[:, :40] = True  # the pattern and the blur's reach from it (3 sigma)
    assert art.blotch_score(image, photo, face, sigma=2.0, exclude=exclude) == pytest.approx(0.0, abs=1e-9)


def test_shadow_edges_are_a_band_around_each_mask_edge():
    m = np.zeros((32, 32), bool)
    m[8:24, 8:24] = True
    edges = art.shadow_edges([m], 2)
    assert edges[8, 16] and edges[6, 16] and edges[9, 16] and not edges[16, 16] and not edges[2, 16]
    assert not art.shadow_edges([np.zeros((32, 32), bool)], 2).any()


def test_luminance_change_is_the_log_ratio_of_mean_luminance():
    region = disc()
    assert art.luminance_change(grey(200), grey(100), region) == pytest.approx(math.log(2.0), rel=1e-12)
    assert math.isnan(art.luminance_change(grey(200), grey(100), np.zeros((64, 64), bool)))


def test_key_sun_share_of_a_sun_and_an_ambient():
    d = np.array([0.6, 0.0, 0.8])
    sun = sh.directional_light(d, 1.0)
    ambient = np.zeros((9, 3))
    ambient[0] = 0.4
    normal = np.zeros((2, 2, 3))
    normal[0, 0], normal[0, 1], normal[1, 0] = d, -d, [0.0, 0.0, 1.0]  # [1, 1]: no normal
    # A lone sun: at n = d its 9-term irradiance is 1.0625 times the sun's own max(0, n.d) = 1.
    share = art.key_sun_share(sun, normal)
    assert share[0, 0] == pytest.approx(1 / 1.0625, rel=1e-3) and share[0, 1] == 0.0 and share[1, 1] == 0.0
    both = art.key_sun_share(sun + ambient, normal)
    e_ambient = sh.irradiance(ambient, d)[0]
    assert both[0, 0] == pytest.approx(1.0 / (e_ambient + 1.0625), rel=1e-3)


def test_cast_shadow_response_is_one_for_the_predicted_shadow_and_zero_for_none():
    face = np.ones((20, 20), bool)
    m = np.zeros((20, 20), bool)
    m[:, :5] = True
    lit = grey(150, (20, 20))
    share = np.full((20, 20), 0.5)
    shadowed = lit.copy()
    shadowed[m] = 75  # half of 150: the sun's share removed
    assert art.cast_shadow_response(shadowed, lit, face, m, share) == pytest.approx(1.0, rel=1e-12)
    assert art.cast_shadow_response(lit, lit, face, m, share) == pytest.approx(0.0, abs=1e-12)
    tiny = np.zeros((20, 20), bool)
    tiny[0, 0] = True  # 1 of 400 face pixels: below the 3% a map must cover
    assert math.isnan(art.cast_shadow_response(shadowed, lit, face, tiny, share))
    # Shading that darkens toward the map's side, no cast shadow: only the 3 px ring around the map (columns 5-7)
    # counts, not the far side of the face (against which the same image reads as half a shadow, 0.53).
    ramp = (lit * (0.5 + 0.5 * np.arange(20) / 19)[None, :, None]).astype(np.float64)
    y = ramp[..., 0] / 255
    want = (y[:, 5:8].mean() - y[:, :5].mean()) / (150 / 255 * 0.5)
    assert art.cast_shadow_response(ramp.round().astype(np.uint8), lit, face, m, share) == pytest.approx(want, abs=0.01)
    assert want < 0.25  # against the rest of the whole face it would read as half a shadow
    # A light whose key sun gives 1% of the light predicts a darkening of 0.006: too little to take a ratio over.
    assert math.isnan(art.cast_shadow_response(shadowed, lit, face, m, np.full((20, 20), 0.01)))
