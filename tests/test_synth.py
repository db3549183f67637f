"""SynthFaces: lights, appearance, and the generator's ground truth."""

import numpy as np
import pytest

from difareli import sh
from difareli.synth import appearance as ap
from difareli.synth import lights as li

# ------------------------------------------------------------------------------------------------ lights


def _sphere(n=500):
    v = np.random.default_rng(1).standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_light_gt_is_ambient_plus_sun():
    light = li.sample_light(np.random.default_rng(0), "hard")
    assert light.has_sun and abs(np.linalg.norm(light.sun_dir) - 1) < 1e-12
    want = light.ambient + sh.directional_light(light.sun_dir, light.sun_rgb)
    np.testing.assert_allclose(light.sh(), want, rtol=1e-6, atol=1e-7)
    # A surface facing the sun gets ambient + ~sun (the SH cosine lobe overshoots by 1/16 exactly at n = d).
    e = sh.irradiance(light.sh().astype(np.float64), light.sun_dir)
    e_amb = sh.irradiance(light.ambient, light.sun_dir)
    np.testing.assert_allclose(e - e_amb, 1.0625 * light.sun_rgb, rtol=1e-5)


def test_every_category_is_physical():
    rng = np.random.default_rng(5)
    n = _sphere()
    for cat in li.CATEGORIES:
        for _ in range(20):
            light = li.sample_light(rng, cat)
            amb = sh.irradiance(light.ambient, n)
            assert amb.min() >= 0, cat  # no negative ambient light anywhere
            assert np.all(light.sun_rgb >= 0)
    # Rim light comes from behind (z < 0), grazing from nearly the side, dim is dim.
    rim = li.sample_light(rng, "rim")
    assert rim.sun_dir[2] < 0
    graze = li.sample_light(rng, "grazing")
    assert abs(graze.sun_dir[2]) < np.sin(np.radians(20)) + 1e-9
    dim = li.sample_light(rng, "dim")
    assert sh.irradiance(dim.sh().astype(np.float64), n).max() < 0.5


def test_light_distribution_and_streams():
    cats = [li.sample_light(li.light_rng(0, g, 0)).category for g in range(400)]
    frac = {c: cats.count(c) / len(cats) for c in li.CATEGORIES}
    assert abs(frac["hard"] - 0.30) < 0.08 and all(f > 0 for f in frac.values())
    a = li.sample_light(li.light_rng(0, 3, 1))
    b = li.sample_light(li.light_rng(0, 3, 1))
    c = li.sample_light(li.light_rng(0, 3, 2))
    np.testing.assert_array_equal(a.sh(), b.sh())
    assert not np.allclose(a.sh(), c.sh())
    with pytest.raises(ValueError, match="unknown light category"):
        li.sample_light(np.random.default_rng(0), "neon")


def test_direction_convention():
    np.testing.assert_allclose(li.direction(0, 0), [0, 0, 1], atol=1e-12)    # from the viewer
    np.testing.assert_allclose(li.direction(90, 0), [1, 0, 0], atol=1e-12)   # from image right
    np.testing.assert_allclose(li.direction(0, 90), [0, 1, 0], atol=1e-12)   # from above


# ------------------------------------------------------------------------------------------------ appearance


def test_skin_tones_span_light_to_dark():
    rng = np.random.default_rng(0)
    lum = [ap.skin_colour(t, rng) @ [0.2126, 0.7152, 0.0722] for t in (0.0, 0.5, 1.0)]
    assert lum[0] > 0.6 and lum[2] < 0.15 and lum[0] > lum[1] > lum[2]
    tones = [ap.sample_appearance(np.random.default_rng([9, k])).skin_tone for k in range(200)]
    assert min(tones) < 0.1 and max(tones) > 0.9


def test_noise_deterministic_smooth_and_bounded():
    p = np.random.default_rng(0).uniform(-3, 3, (2000, 3))
    a, b = ap.value_noise(p, 7), ap.value_noise(p, 7)
    np.testing.assert_array_equal(a, b)
    assert a.min() >= -1 and a.max() <= 1 and a.std() > 0.2
    assert not np.allclose(a, ap.value_noise(p, 8))
    # Smooth: a tiny step changes the value a little (C1 interpolation), not a lattice jump.
    d = np.abs(ap.value_noise(p + 1e-4, 7) - a)
    assert d.max() < 0.01


def test_albedo_image_parts_and_off_mesh():
    from difareli.encodings import PART_INDEX

    app = ap.sample_appearance(np.random.default_rng(2))
    label = np.zeros((8, 8), np.int32)
    label[2:6, 2:6] = PART_INDEX["skin"]
    label[2:4, 2:4] = PART_INDEX["hair"]
    hit = label > 0
    v, u = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
    points = np.stack([u * 0.05, -v * 0.05, np.zeros_like(u, float)], -1)
    alb = ap.albedo_image(app, label, points, hit, size=1.0)
    assert alb.dtype == np.float32 and np.all(alb[~hit] == 0)
    skin = alb[label == PART_INDEX["skin"]]
    # Skin stays within the texture amplitude of its base colour.
    rel = skin / app.colours["skin"]
    assert np.all(np.abs(rel - 1) <= app.blotch + app.grain + 1e-6)


def test_backgrounds_include_extremes_and_are_resolution_independent():
    bgs = [ap.sample_background(np.random.default_rng([4, k])) for k in range(300)]
    means = np.array([b.render(16, 16).mean() for b in bgs])
    assert (means < 0.08).any() and (means > 0.9).any()
    assert {b.kind for b in bgs} == set(ap.BACKGROUND_KINDS)
    tex = next(b for b in bgs if b.kind == "texture")
    small, big = tex.render(16, 16), tex.render(64, 64)
    # The 64px render averaged down to 16px matches the 16px render (same pattern, not re-randomised).
    down = big.reshape(16, 4, 16, 4, 3).mean((1, 3))
    assert np.abs(down - small).mean() < 0.03
