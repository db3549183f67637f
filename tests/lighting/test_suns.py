"""``lighting.suns.Suns``: a SynthFaces header read back into the light that rendered it."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.errors import UserError
from difareli.lighting import sh
from difareli.lighting.suns import Suns, sun_direction
from difareli.synth.lights import add_suns, extra_sun_rng, light_rng, sample_light


@pytest.mark.parametrize("index", range(6))
def test_header_round_trip(index):
    """The suns and ambient read from a light's header and its SH give back that light's suns, ambient and SH."""
    light = add_suns(sample_light(light_rng(7, 0, index)), extra_sun_rng(7, 0, index))
    suns = Suns.from_header(light.meta(), light.sh())
    want = light.suns()
    if not want:  # an ambient-only light: no sun to block
        assert suns is None
        return
    assert len(suns.dirs) == len(want)
    for (d, c), d2, c2 in zip(want, suns.dirs, suns.rgbs):
        np.testing.assert_allclose(d2, d / np.linalg.norm(d), atol=2e-6)  # the header rounds to 6 decimals
        np.testing.assert_allclose(c2, c, atol=2e-6)
    np.testing.assert_allclose(suns.ambient, light.ambient, atol=1e-4)  # the SH is float32
    np.testing.assert_allclose(suns.sh(), light.sh(), atol=1e-5)
    n = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    lam = light.ambient
    e = sh.irradiance(lam, n) + sum(np.maximum(n @ d, 0)[:, None] * c for d, c in want)
    np.testing.assert_allclose(suns.irradiance(n), e, atol=1e-4)


def test_no_lit_sun_and_bad_suns():
    assert Suns.from_header({"sun_dir": [0, 0, 1], "sun_rgb": [0, 0, 0]}, np.zeros((9, 3))) is None
    with pytest.raises(UserError, match="non-zero directions"):
        Suns(np.zeros((1, 3)), np.ones((1, 3)), np.zeros((9, 3)))
    with pytest.raises(UserError, match="non-zero directions"):
        Suns(np.ones((2, 3)), np.ones((1, 3)), np.zeros((9, 3)))


def test_of_sh_is_one_sun_toward_the_radiance_peak_carrying_all_the_light():
    light = sh.directional_light(np.array([0.3, 0.4, 0.866]), 2.0)
    suns = Suns.of_sh(light)
    # The same direction (one finder); to rounding: numpy's SIMD paths differ by a few ulps across CPUs.
    np.testing.assert_allclose(suns.dirs[0], sun_direction(light), rtol=0, atol=1e-12)
    assert _angle(suns.dirs[0], np.array([0.3, 0.4, 0.866])) < 0.3
    assert not suns.ambient.any() and len(suns.dirs) == 1


def _angle(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


@pytest.mark.parametrize("seed", range(4))
def test_sun_direction_finds_a_sun_where_band_1_is_pulled_away(seed):
    """A sun's band-limited radiance peaks at the sun (to the grid's refinement); a uniform ambient does not move
    it; a weaker second sun pulls band 1 (the mean direction) much further than the peak; rotating the light
    rotates the peak; a flat light has none (+z)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    alone = sh.directional_light(d, 1.0)
    assert _angle(sun_direction(alone), d) < 0.3
    ambient = np.zeros((9, 3))
    ambient[0] = 0.5
    assert _angle(sun_direction(alone + ambient), d) < 0.3
    fill = np.cross(d, rng.normal(size=3))
    fill /= np.linalg.norm(fill)  # 90 degrees from the sun
    both = alone + ambient + sh.directional_light(fill, 0.4)
    assert _angle(sun_direction(both), d) < 10.0 < _angle(sh.dominant_direction(both), d)
    R = sh.rotation_yaw(37.0) @ sh.rotation_roll(-21.0)
    assert _angle(sun_direction(sh.rotate(both, R)), R @ sun_direction(both)) < 0.3
    np.testing.assert_array_equal(sun_direction(ambient), [0.0, 0.0, 1.0])
