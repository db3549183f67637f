"""Named lights made plausible for the face they light (lighting.presets.plausible): never negative irradiance on a
face's normals or on a sphere's visible half, the darkest normal at least FILL of the mean, and the source light's
mean irradiance on the face kept."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.data.store import EncodingStore
from difareli.lighting import sh
from difareli.lighting.presets import DIRECTIONS, FILL, NAMES, VISIBLE, face_normals, plausible, preset_light, toward
from difareli.relight.targets import target_lights


def sources(rng) -> list[np.ndarray]:
    """Source lights as photos give them: a strong frontal key with little ambient (whose own turn to 'rim' is
    negative on most of a face), a side-lit coloured one, and random estimator-like lights."""
    key = sh.directional_light([0.1, 0.2, 1.0], 1.0)
    key[0] *= 0.3  # a photo estimator's light: a large linear term over a small ambient
    side = sh.directional_light([-1.0, 0.3, 0.5], [1.0, 0.8, 0.6])
    side[0] += [0.5, 0.45, 0.4]
    rand = [sh.directional_light(rng.normal(size=3), rng.uniform(0.5, 1.5)) + rng.normal(0, 0.05, (9, 3))
            for _ in range(4)]
    for light in rand:
        light[0] += rng.uniform(0.3, 1.0)
    return [key, side, *rand]


def face_normal_sets(synth_store) -> list[np.ndarray]:
    store = EncodingStore.open(synth_store)
    return [store.read(i, ["normal"])["normal"] for i in store.ids()[:3]]


def check(light: np.ndarray, like: np.ndarray, normals: np.ndarray | None) -> None:
    n = face_normals(normals)
    e = sh.irradiance(light, n)
    assert e.min() >= 0 and sh.irradiance(light, VISIBLE).min() >= -1e-9
    grey = e.mean(-1)
    assert grey.min() >= FILL * grey.mean() - 1e-6 * grey.mean()
    own = sh.irradiance(like, n).mean()
    assert e.mean() == pytest.approx(own, rel=1e-6)  # the source's energy on the face kept


def test_every_named_light_is_non_negative_and_keeps_the_face_energy(rng, synth_store):
    for like in sources(rng):
        for normals in [None, *face_normal_sets(synth_store)]:
            for name in NAMES:
                check(preset_light(name, like, normals), like, normals)
            check(preset_light("sunset", like, normals, yaw=120.0), like, normals)
            check(toward(like, [0.3, -0.9, 0.2], normals), like, normals)


def test_the_raw_turn_was_negative_and_the_direction_and_colour_stay(rng):
    key = sources(rng)[0]
    raw = sh.light_toward(key, DIRECTIONS["rim"][0])
    assert (sh.irradiance(raw, VISIBLE).mean(-1) < 0).mean() > 0.5  # the case the issue met: 'rim' negative
    for name, (direction, _) in DIRECTIONS.items():
        np.testing.assert_allclose(sh.dominant_direction(preset_light(name, key)),
                                   np.asarray(direction) / np.linalg.norm(direction), atol=1e-6)
    side = sources(rng)[1]
    out = preset_light("left", side)
    np.testing.assert_allclose(out[1:], sh.light_toward(side, DIRECTIONS["left"][0])[1:] * (out[1, 0] / sh.light_toward(
        side, DIRECTIONS["left"][0])[1, 0]), rtol=1e-9)  # one factor on every channel: the colour stays


def test_a_light_that_needs_nothing_is_only_scaled():
    light = sh.directional_light([0, 0, 1], 1.0)
    light[0] += 3.0  # plenty of ambient: its darkest normal already has more than FILL of the mean
    out = plausible(light, 2 * light)
    np.testing.assert_allclose(out, 2 * light, rtol=1e-9)


def test_the_relight_targets_pass_the_face_normals(synth_store):
    like = sources(np.random.default_rng(1))[0]
    normals = face_normal_sets(synth_store)[0]
    got = target_lights(like, light="top", normals=normals)
    np.testing.assert_allclose(got, preset_light("top", like, normals))
    assert not np.allclose(got, preset_light("top", like))  # the face's normals, not the sphere's, set the scale
    np.testing.assert_allclose(target_lights(like, direction=[1, 0, 0], normals=normals), toward(like, [1, 0, 0],
                                                                                                   normals))


def test_a_key_behind_the_face_lights_it_by_the_fill_alone(synth_store):
    """A light turned behind the head: its linear SH term had lit the face normals that face away from it least
    (forehead, nose bridge) several times more than the rest (issue 61's bright patch); the face now gets the fill
    alone, its energy kept and the light's direction still readable. A light some normal faces keeps its key."""
    from difareli.lighting.presets import behind

    normals = face_normal_sets(synth_store)[0]
    n = face_normals(normals)
    key = sources(np.random.default_rng(2))[0]
    raw = sh.light_toward(key, [0.0, 0.35, -1.0])
    assert (n @ sh.dominant_direction(raw)).max() < 0  # every face normal faces away from it
    e = sh.irradiance(raw, n).mean(-1)
    assert e.max() - e.min() > e.mean()  # the raw turn: a strong gradient over normals it cannot light
    out = plausible(raw, key, normals)
    e = sh.irradiance(out, n).mean(-1)
    assert e.max() - e.min() < 1e-4 * e.mean()
    np.testing.assert_allclose(sh.dominant_direction(out), sh.dominant_direction(raw), atol=1e-6)
    for name in ("left", "right", "top", "front"):
        lit = sh.light_toward(key, DIRECTIONS[name][0])
        assert behind(lit, n) == 1.0
