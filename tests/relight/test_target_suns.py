"""A target's key sun (``Targets.suns``): its shadow map is marched toward the given direction instead of the
light's radiance peak, in one batch with the other targets, the shading still from the SH light."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.errors import UserError, check_choice
from difareli.lighting import sh
from difareli.lighting.suns import sun_direction
from difareli.relight.targets import Targets
from difareli.render.retarget import retarget
from difareli.render.camera import OrthoCamera
from difareli.render.screen_shadow import march_shadows
from tests.render.test_sun_fit import _direction, _scene

NAMES = ["shading", "shadow_map"]


def _arrays():
    a = _scene(_direction(45, 0), _direction(55, 110))
    return {**{k: a[k] for k in ("normal", "depth", "cam")}, "shadow": np.array([3.0], np.float32)}


def test_a_given_sun_is_where_the_map_is_marched_and_the_shading_stays_the_lights():
    arrays = _arrays()
    light = sh.directional_light(_direction(20, 30), 1.0)
    sun = _direction(50, 200)
    hit = arrays["depth"] != 0
    toward = lambda d: march_shadows(arrays["depth"].astype(np.float64), hit, OrthoCamera(1.0, 0.0, 0.0),  # noqa: E731
                                     d[None], normal=arrays["normal"].astype(np.float64))[0]
    given = Targets.of([light, light], [3.0, 3.0], suns=[sun, None]).retarget(arrays, NAMES)  # one batched march
    peak = retarget(arrays, NAMES, light, 3.0)
    assert toward(sun).sum() > 30 and (toward(sun) != toward(sun_direction(light))).sum() > 30
    np.testing.assert_array_equal(given[0]["shadow_map"] > 0, toward(sun))          # toward the given sun
    np.testing.assert_array_equal(given[1]["shadow_map"], peak["shadow_map"])       # None: the peak
    np.testing.assert_array_equal(given[1]["shadow_map"] > 0, toward(sun_direction(light)))
    np.testing.assert_array_equal(given[0]["shading"], peak["shading"])             # shading: the SH light
    single = retarget(arrays, NAMES, light, 3.0, sun=sun)                            # unbatched: the same map
    np.testing.assert_array_equal(single["shadow_map"], given[0]["shadow_map"])
    one = Targets.of([light, light], [3.0, 3.0], suns=[sun, None]).take(0, 1)
    assert len(one) == 1 and one.suns[0] is not None and np.allclose(one.suns[0], sun)


def test_sun_directions_are_checked():
    light = sh.directional_light(_direction(20, 30), 1.0)
    with pytest.raises(UserError, match="2 target lights but 1 sun directions"):
        Targets.of([light, light], suns=[None])
    with pytest.raises(UserError, match="non-zero 3-vector"):
        Targets.of([light], suns=[np.zeros(3)])
    got = Targets.of([light], suns=[[0.0, 0.0, 2.0]]).suns[0]
    np.testing.assert_allclose(got, [0.0, 0.0, 1.0])


def test_a_rotation_videos_key_sun_turns_with_its_light():
    """``rotation_targets(..., sun=d)``: frame i's map is marched toward ``R_i d``, the rotation that turns the SH
    light (its direction turns the same way); yaw 90 degrees takes +z to +x."""
    from difareli.relight.request import rotation_targets

    light = sh.directional_light(_direction(30, 40), 1.0)
    sun = _direction(35, 80)
    for axis in sh.AXES:
        angles, rots = sh.rotation_frames(axis, 8)
        targets, _ = rotation_targets({"light": light, "shadow": np.array([3.0])}, axis, 8, given=3.0, sun=sun)
        np.testing.assert_allclose(np.stack(targets.suns), rots @ sun, atol=1e-12)
        np.testing.assert_allclose(targets.suns[0], sun, atol=1e-12)
        # Band 1's direction is exact; the radiance peak is searched on a point set (within a degree).
        np.testing.assert_allclose(sh.dominant_direction(targets.lights), rots @ sh.dominant_direction(light),
                                   atol=1e-9)
        np.testing.assert_allclose(np.stack([sun_direction(l) for l in targets.lights]),
                                   rots @ sun_direction(light), atol=0.02)
        plain, _ = rotation_targets({"light": light, "shadow": np.array([3.0])}, axis, 8, given=3.0)
        assert plain.suns is None
    np.testing.assert_allclose(sh.rotation_frames("yaw", 4)[1][1] @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], atol=1e-12)
    with pytest.raises(UserError, match="rotation axis"):
        sh.rotation_frames("pitch", 4)


def test_key_sun_needs_the_images_face_and_the_choice_is_checked():
    from difareli.lighting.light_fit import LightFit
    from difareli.render import sun_fit

    a = _scene(_direction(45, 0), _direction(55, 110))
    fit = LightFit(albedo=0.6, parts=())
    light = fit(a)
    found = sun_fit.key_sun(a, light, fit=fit)
    np.testing.assert_array_equal(found.direction, sun_fit.fit_sun(a, light, fit=fit).direction)
    assert found.note.startswith("marched toward the key sun found from the image's cast shadows")
    assert sun_fit.key_sun({k: v for k, v in a.items() if k != "face_mask"}, light, fit=fit) is None
    assert sun_fit.PEAK_NOTE == "marched toward the light's radiance peak"
    assert check_choice("peak", "target.sun", sun_fit.TARGET_SUNS) == "peak"
    with pytest.raises(UserError, match=r"^target.sun='east': use one of shadows, peak$"):
        check_choice("east", "target.sun", sun_fit.TARGET_SUNS)
