"""Turning a light toward a direction (the app's light picker): the rotation between two directions, a light's
dominant direction moved where asked with its ambient and strength kept, and huge components not overflowing."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.data.encodings import SHADOW_C_HI, SHADOW_C_LO, denormalise_c, normalise_c
from difareli.errors import UserError
from difareli.lighting import sh


def test_light_toward_points_the_dominant_direction_where_asked(rng):
    for _ in range(20):
        light = sh.directional_light(rng.normal(size=3), [1.0, 0.9, 0.8]) + rng.normal(scale=0.05, size=(9, 3))
        light[0] += 0.8  # some ambient, as the fitted photo lights have
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        out = sh.light_toward(light, d)
        np.testing.assert_allclose(sh.dominant_direction(out), d, atol=1e-6)
        np.testing.assert_allclose(out[0], light[0], atol=1e-9)  # a rotation keeps the ambient
        np.testing.assert_allclose(np.linalg.norm(out[1:4]), np.linalg.norm(light[1:4]), rtol=1e-9)


@pytest.mark.parametrize("b", [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.3, -0.4, 0.5]])
def test_rotation_between_is_a_rotation_taking_a_to_b(b):
    a, b = np.array([0.0, 0.0, 1.0]), np.asarray(b) / np.linalg.norm(b)
    r = sh.rotation_between(a, b)
    np.testing.assert_allclose(r @ a, b, atol=1e-12)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_a_large_but_valid_direction_is_not_turned_around():
    """Components >= ~1e154 overflowed the norm to inf; the light then turned a half turn."""
    own = sh.directional_light([0, 0, 1], 1.0)
    own[0] += 1.0
    np.testing.assert_allclose(sh.dominant_direction(sh.light_toward(own, [1e160, 0, 0])), [1, 0, 0], atol=1e-6)


@pytest.mark.parametrize("bad", [[0, 0, 0], [1, float("nan"), 0], [1, 0]])
def test_no_direction_is_a_user_error(bad):
    with pytest.raises(UserError, match="not a finite non-zero 3-vector"):
        sh.light_toward(sh.directional_light([0, 0, 1], 1.0), bad)


def test_a_shadow_strength_is_the_normalised_c():
    assert denormalise_c(0.0) == pytest.approx(SHADOW_C_LO) and denormalise_c(1.0) == pytest.approx(SHADOW_C_HI)
    assert float(normalise_c(denormalise_c(0.37))) == pytest.approx(0.37)
    assert denormalise_c(5.0) == pytest.approx(SHADOW_C_HI)  # clipped
    assert float(normalise_c(denormalise_c(0.25, (-5.0, -1.0)), (-5.0, -1.0))) == pytest.approx(0.25)
