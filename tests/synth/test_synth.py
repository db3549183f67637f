"""SynthFaces: lights, appearance, and the generator's ground truth."""

import numpy as np
import pytest

from difareli.lighting import sh
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
    from difareli.data.encodings import PART_INDEX

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


# ------------------------------------------------------------------------------------------------ generator

from difareli.data.encodings import FOREGROUND_PARTS, PART_INDEX  # noqa: E402
from difareli.synth import generator as gen  # noqa: E402
from difareli.synth import config as synth_config  # noqa: E402
from difareli.synth import subject as synth_subject  # noqa: E402
from difareli.render import cast_shadows  # noqa: E402
from difareli.data.encodings import normalise_c  # noqa: E402
from difareli.data import protocols as sp  # noqa: E402

CFG = synth_config.SynthConfig(subjects=4, lights=3, resolution=48, seed=11)


@pytest.fixture(scope="module")
def subject():
    return synth_subject.build_subject(1, CFG)


@pytest.fixture(scope="module")
def records():
    return {rid: (arr, meta) for rid, arr, meta in gen.render_records(1, [0, 1, 2], CFG, "train")}


def test_records_deterministic_and_seeded(records):
    again = {rid: arr for rid, arr, _ in gen.render_records(1, [2], CFG, "train")}
    for name, a in again["s00001_l2"].items():
        np.testing.assert_array_equal(a, records["s00001_l2"][0][name], err_msg=name)
    other = synth_config.SynthConfig(subjects=4, lights=3, resolution=48, seed=12)
    diff = next(arr for _, arr, _ in gen.render_records(1, [2], other, "train"))
    assert not np.array_equal(diff["shape"], records["s00001_l2"][0]["shape"])


def test_lights_of_a_subject_share_everything_but_light(records):
    arrs = [records[f"s00001_l{j}"][0] for j in range(3)]
    for name in ("masks", "cam", "shape", "identity", "normal", "face_mask"):
        for a in arrs[1:]:
            np.testing.assert_array_equal(a[name], arrs[0][name], err_msg=name)
    assert not np.allclose(arrs[0]["light"], arrs[1]["light"])
    assert (abs(np.linalg.norm(arrs[0]["identity"]) - 1) < 1e-6
            and arrs[0]["identity"].shape == (synth_config.IDENTITY_DIM,))
    # Subjects 0 and 1 form one light group: same lights, different faces.
    a0 = next(arr for _, arr, _ in gen.render_records(0, [1], CFG, "train"))
    np.testing.assert_array_equal(a0["light"], arrs[1]["light"])
    assert not np.array_equal(a0["shape"], arrs[1]["shape"])


def test_shading_and_background_from_stored_encodings(records, subject):
    for arr, _ in records.values():
        region = np.any(arr["normal"] != 0, axis=-1)
        want = 0.7 * sh.irradiance(arr["light"], arr["normal"])
        np.testing.assert_array_equal(arr["shading"][region], want[region].astype(np.float32))
        assert np.all(arr["shading"][~region] == 0)
        assert region.sum() > 0.15 * region.size and np.all(region <= subject.gbuffer.hit)
        np.testing.assert_allclose(np.linalg.norm(arr["normal"][region], axis=-1), 1, atol=1e-5)
        fg = np.isin(arr["masks"], [PART_INDEX[p] for p in FOREGROUND_PARTS])
        assert np.all(arr["background"][fg] == 0)
        np.testing.assert_array_equal(arr["background"][~fg], arr["image"][~fg])
        assert arr["face_mask"].sum() > 0 and np.all(arr["masks"][arr["face_mask"]] > 0)


def test_image_is_albedo_times_irradiance(subject):
    gb = subject.gbuffer
    n = gb.normal.astype(np.float64)
    # No sun: the image is albedo x irradiance of the stored light, exactly up to uint8 rounding.
    amb = li.ambient_sh(np.random.default_rng(0), [0.7, 0.6, 0.5], gradient=0.4, band2=0.2)
    soft = li.Light("soft", amb, np.array([0.0, 0.0, 1.0]), np.zeros(3))
    arr, _ = synth_subject.shade(subject, soft, None, CFG)
    want = np.clip(subject.albedo * sh.irradiance(arr["light"].astype(np.float64), n), 0, 1) * 255
    assert np.abs(arr["image"][gb.hit] - want[gb.hit]).max() <= 0.5 + 1e-3
    np.testing.assert_array_equal(arr["image"][~gb.hit], np.round(subject.background[~gb.hit] * 255))
    assert arr["shadow"][0] == pytest.approx(synth_config.C_LO, abs=1e-4) and not arr["shadow_map"].any()
    # Hard side light from image left and above: cast shadows lose exactly the sun term.
    d = li.direction(-60, 30)
    hard = li.Light("hard", amb * 0.3, d, np.array([1.0, 1.0, 1.0]))
    cast = cast_shadows(subject.scene, gb, d[None])[0]
    arr, _ = synth_subject.shade(subject, hard, cast, CFG)
    e_amb = sh.irradiance(hard.ambient, n)
    e_sun = np.maximum(n @ d, 0)[..., None] * hard.sun_rgb
    lit = np.clip(subject.albedo * (e_amb + e_sun * (~cast)[..., None]), 0, 1) * 255
    assert np.abs(arr["image"][gb.hit] - lit[gb.hit]).max() <= 0.5 + 1e-3
    sm = arr["shadow_map"]
    assert cast.sum() > 10 and np.all((sm > 0) == cast)
    assert synth_config.C_LO < arr["shadow"][0] < synth_config.C_HI
    np.testing.assert_allclose(sm[cast], normalise_c(arr["shadow"][0]), rtol=1e-6)
    # Shadows follow the sun: with the sun on the image left, shadowed pixels sit right of lit ones
    # on average, and mirroring the sun mirrors that.
    cols = np.arange(gb.hit.shape[1])[None, :].repeat(gb.hit.shape[0], 0)
    lit_px = gb.hit & (n @ d > 0) & ~cast
    assert cols[cast].mean() > cols[lit_px].mean()
    d2 = d * [-1, 1, 1]
    cast2 = cast_shadows(subject.scene, gb, d2[None])[0]
    assert cols[cast2].mean() < cols[gb.hit & (n @ d2 > 0) & ~cast2].mean()


def test_generate_resume_and_protocols(tmp_path):
    out = tmp_path / "sf"
    r1 = gen.generate(str(out), 4, 2, 32, seed=3, workers=1, splits={"train": 0.5, "val": 0.0, "test": 0.5})
    assert (r1.written, r1.skipped, r1.problems) == (8, 0, [])
    from difareli.data.store import EncodingStore

    store = EncodingStore.open(out)
    assert store.verify(check_values=True) == [] and len(store) == 8
    # Delete one record: a rerun writes exactly it and skips the rest.
    import shutil

    shutil.rmtree(store.records_dir / "s00002_l1")
    r2 = gen.generate(str(out), 4, 2, 32, seed=3, splits={"train": 0.5, "val": 0.0, "test": 0.5})
    assert (r2.written, r2.skipped) == (1, 7)
    r3 = gen.generate(str(out), 4, 2, 32, seed=3, splits={"train": 0.5, "val": 0.0, "test": 0.5})
    assert (r3.written, r3.skipped) == (0, 8)
    import json

    proto = json.loads((out / sp.PROTOCOLS_FILE).read_text())
    splits = json.loads((out / sp.SPLITS_FILE).read_text())["splits"]
    assert len(splits["test"]) == 2 and not set(splits["test"]) & set(splits["train"])
    assert len(proto["same_subject"]) == 2 * 2 and len(proto["different_subject"]) == 2 * 2
    for pair in proto["same_subject"] + proto["different_subject"]:
        for key in ("source", "light_source", "target"):
            assert store.has(pair[key])
            assert store.meta(pair[key])["split"] == "test"
        # GT relit pair: target is the source's subject under the light-source's light.
        np.testing.assert_array_equal(store.read(pair["target"], ["light"])["light"],
                                      store.read(pair["light_source"], ["light"])["light"])
        assert store.meta(pair["target"])["subject"] == store.meta(pair["source"])["subject"]
    with pytest.raises(synth_config.ConfigError, match="seed"):
        gen.generate(str(out), 4, 2, 32, seed=4, splits={"train": 0.5, "val": 0.0, "test": 0.5})
