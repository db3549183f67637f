"""Baselines and the light fit on closed-form Lambertian cases built from a SynthFaces record's normals."""

import numpy as np
import pytest

from difareli.lighting import sh
from difareli.evaluation.baselines import (DiffusionMethod, Identity, LambertianRatio, Method, Oracle, build_method,
                                           ratio_relight)
from difareli.evaluation.pairs import StoredFace, irradiance_error
from difareli.lighting.albedo import synthfaces_mean_skin_albedo
from difareli.lighting.light_fit import LightFit
from difareli.data.encodings import PART_INDEX
from difareli.data.store import EncodingStore

ALBEDO = np.array([0.6, 0.45, 0.35])


@pytest.fixture(scope="module")
def geometry(synth_store):
    """(store, record id, normals, bool mask of stored normals, face_mask) of the first test record."""
    store = EncodingStore.open(synth_store)
    rid = store.ids(split="test")[0]
    a = store.read(rid, ["normal", "face_mask", "masks"])
    n = np.asarray(a["normal"], dtype=np.float64)
    return store, rid, n, np.linalg.norm(n, axis=-1) > 0.5, np.asarray(a["face_mask"]), np.asarray(a["masks"])


def _light(direction, sun=(0.5, 0.45, 0.4), ambient=(0.55, 0.5, 0.5)):
    """An SH light: ambient (band 0) plus a directional sun; irradiance stays in (0.2, 1.3) on a face."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    light = sh.directional_light(d, np.asarray(sun))
    light[0] += np.asarray(ambient)
    return light


def _render(normal, known, light, albedo=ALBEDO, background=None):
    """uint8 image = round(255 * albedo * E(n)) where a normal is stored, ``background`` elsewhere."""
    img = np.zeros(normal.shape, np.float64) if background is None else background / 255.0
    img = img.copy()
    img[known] = albedo * sh.irradiance(light, normal[known])
    assert img[known].max() < 1 and img[known].min() > 0.02  # no clipping: the linear model holds exactly
    return np.round(img * 255).astype(np.uint8)


def test_light_fit_recovers_known_light(geometry):
    store, rid, n, known, face, masks = geometry
    truth = _light([0.4, 0.5, 0.8])
    arrays = {"image": _render(n, known, truth), "normal": n, "face_mask": face, "masks": masks}
    est = LightFit(albedo=tuple(ALBEDO))(arrays)
    rel, gain_free = irradiance_error(est, truth, n, known & face)
    assert rel < 5e-3 and gain_free < 5e-3  # only uint8 quantisation separates them
    # The prior's scale is the light's inverse scale: twice the albedo, half the light (exactly, by linearity).
    half = LightFit(albedo=tuple(2 * ALBEDO))(arrays)
    np.testing.assert_allclose(half, est / 2, rtol=1e-9, atol=1e-12)
    rel2, gain_free2 = irradiance_error(half, truth, n, known & face)
    assert rel2 == pytest.approx(0.5, abs=5e-3) and gain_free2 == pytest.approx(gain_free, abs=1e-9)


def test_light_fit_uses_only_unclipped_skin(geometry):
    store, rid, n, known, face, masks = geometry
    truth = _light([-0.5, 0.3, 0.8])
    img = _render(n, known, truth)
    # Corrupt every non-skin face pixel and clip a few skin pixels: neither may enter the fit.
    fit = LightFit(albedo=tuple(ALBEDO), robust_iters=0)
    usable = fit.pixels({"image": img, "normal": n, "face_mask": face, "masks": masks})[0].shape[0]
    bad = img.copy()
    other = face & known & ~np.isin(masks, [PART_INDEX["skin"], PART_INDEX["nose"]])
    bad[other] = 0
    bad[tuple(np.argwhere(face & known & (masks == PART_INDEX["skin"]))[:5].T)] = 255
    est = fit({"image": bad, "normal": n, "face_mask": face, "masks": masks})
    assert irradiance_error(est, truth, n, known & face)[0] < 5e-3
    assert fit.pixels({"image": bad, "normal": n, "face_mask": face, "masks": masks})[0].shape[0] == usable - 5


def test_ratio_relight_is_exact_without_cast_shadows(geometry, rng):
    store, rid, n, known, face, masks = geometry
    l1, l2 = _light([0.6, 0.3, 0.75]), _light([-0.5, -0.2, 0.85], sun=(0.7, 0.6, 0.5))
    background = rng.integers(0, 256, n.shape).astype(np.float64)
    img1, img2 = _render(n, known, l1, background=background), _render(n, known, l2, background=background)
    relit = ratio_relight(img1, n, l1, l2)
    ratio = (sh.irradiance(l2, n[known]) / sh.irradiance(l1, n[known]))
    # img1 carries <= 0.5 level of rounding, scaled by the ratio; img2 and the output round once more.
    diff = np.abs(relit[known].astype(int) - img2[known].astype(int))
    assert (diff <= np.floor(0.5 * ratio + 1.0)).all() and diff.mean() < 0.6
    assert (relit[~known] == img1[~known]).all()  # outside the face: unchanged
    # A common scale on both lights (the albedo prior's) cancels.
    np.testing.assert_array_equal(ratio_relight(img1, n, 4 * l1, 4 * l2), relit)
    # Through the Method interface with the stored geometry and given lights.
    assert isinstance(LambertianRatio(), Method)


def test_ratio_floor_guards_dark_sources(geometry):
    store, rid, n, known, face, masks = geometry
    img = np.full(n.shape, 40, np.uint8)
    src = _light([0, 0, 1], sun=(1.0, 1.0, 1.0), ambient=(-0.8, -0.8, -0.8))  # E_s < 0 toward grazing normals
    tgt = _light([0.3, 0.2, 0.9])
    e_s, e_t = sh.irradiance(src, n[known]), sh.irradiance(tgt, n[known])
    floor = 0.05 * np.median(e_s, axis=0)
    low = e_s < floor
    assert low.any() and (~low).any() and (floor > 0).all()
    out = ratio_relight(img, n, src, tgt)[known].astype(float)
    # Floored pixels get input * E_t / floor (finite, not the sign-flipped or exploding raw ratio) ...
    want_low = np.round(np.clip(40 / 255 * e_t / floor, 0, 1) * 255)
    np.testing.assert_array_equal(out[low], np.broadcast_to(want_low, low.shape)[low])
    # ... the others the plain ratio.
    want = np.round(np.clip(40 / 255 * e_t / e_s, 0, 1) * 255)
    np.testing.assert_array_equal(out[~low], want[~low])


def test_identity_oracle_and_factory(synth_store):
    store = EncodingStore.open(synth_store)
    a, b = store.ids(split="test")[:2]
    light = np.zeros((9, 3))
    source, target = StoredFace(store, a), StoredFace(store, b)
    np.testing.assert_array_equal(Identity().relight(source, light), store.read(a, ["image"])["image"])
    np.testing.assert_array_equal(Oracle().relight(source, light, target=target), store.read(b, ["image"])["image"])
    with pytest.raises(ValueError, match="the oracle needs the ground-truth record"):  # no target: refused
        Oracle().relight(source, light)
    m = build_method({"_target_": "difareli.evaluation.baselines.LambertianRatio", "name": None, "min_shading": 0.1},
                     name_suffix="+gt-light")
    assert m.name == "lambertian+gt-light" and m.estimator is None and m.min_shading == 0.1
    fit = LightFit(robust_iters=1)
    assert build_method({"_target_": "difareli.evaluation.baselines.LambertianRatio"}, estimator=fit).estimator is fit
    with pytest.raises(ValueError, match="_target_"):
        build_method({"kind": "identity"})
    with pytest.raises(ValueError, match="not an importable class"):
        build_method({"_target_": "difareli.evaluation.baselines.Nope"})
    with pytest.raises(ValueError, match="checkpoint"):
        build_method({"_target_": "difareli.evaluation.baselines.DiffusionMethod", "checkpoint": None},
                     sampler={"name": "ddim", "steps": 3})
    with pytest.raises(ValueError, match="method.checkpoint must be set"):
        build_method({"_target_": "difareli.evaluation.baselines.DiffusionMethod", "checkpoint": "???"})


def test_method_configs_declare_what_they_consume():
    """Each conf/method/*.yaml builds its class from ``_target_``; the classes declare light / light-fit use."""
    from omegaconf import OmegaConf

    from tests.helpers import CONF

    want = {"identity": (Identity, False, False), "oracle": (Oracle, False, False),
            "lambertian": (LambertianRatio, True, True), "diffusion": (DiffusionMethod, True, False)}
    assert {p.stem for p in (CONF / "method").glob("*.yaml")} == set(want)
    for stem, (cls, light, fit) in want.items():
        cfg = OmegaConf.to_container(OmegaConf.load(CONF / "method" / f"{stem}.yaml"))
        assert cfg["_target_"] == f"difareli.evaluation.baselines.{cls.__name__}"
        assert (cls.needs_light, cls.needs_light_fit) == (light, fit)
    for stem in ("identity", "oracle", "lambertian"):
        m = build_method(OmegaConf.to_container(OmegaConf.load(CONF / "method" / f"{stem}.yaml")))
        assert isinstance(m, want[stem][0]) and m.name == stem


def test_mean_skin_albedo_prior():
    # Trapezoid mean of the 10 Monk swatches (tone uniform, linear interpolation) times the model's scale.
    from difareli.synth.appearance import MONK_SCALE, SKIN_ALBEDO_SCALE

    tones = np.linspace(0, 1, 100001)
    x = tones * 9
    i = np.minimum(x.astype(int), 8)
    sampled = MONK_SCALE[i] * (1 - (x - i))[:, None] + MONK_SCALE[i + 1] * (x - i)[:, None]
    np.testing.assert_allclose(synthfaces_mean_skin_albedo(), sampled.mean(0) * SKIN_ALBEDO_SCALE, atol=1e-5)


def test_a_record_too_small_for_the_light_fit_is_named_with_the_fix(synth_store, tmp_path):
    """A benchmark whose light-source image has too few usable face pixels said 'light fit: only 27 usable face
    pixels (need 30)': no store, no record, no fix. Now the record, its count and what to change."""
    from difareli.errors import UserError
    from difareli.evaluation.benchmark import run_benchmark

    store = EncodingStore.open(synth_store)
    rid = store.ids()[0]
    have = int(LightFit().region(store.read(rid, list(LightFit.ENCODINGS))).sum())
    assert have > 9
    with pytest.raises(UserError) as e:
        LightFit(min_pixels=have + 1).from_store(store, rid)
    assert str(e.value) == (f"store {synth_store}, record {rid}: its image has {have} face pixels the light fit can "
                            f"use (skin and nose, neither clipped nor black), under light_fit.min_pixels={have + 1}; "
                            "a store at a larger resolution gives it more (this one is 32 px), or lower the bound: "
                            f"light_fit.min_pixels={have}")
    assert LightFit(min_pixels=have).from_store(store, rid).shape == (9, 3)  # the bound it names fits
    with pytest.raises(UserError, match=r"^store .*, record s\d+_l\d: its image has \d+ face pixels .* \(this one "
                                        r"is 32 px\)(, or lower the bound: light_fit.min_pixels=\d+)?$"):
        run_benchmark(store, Identity(), ["same_subject"], tmp_path / "b", limit=1, progress=False, grid_pairs=0,
                      estimator=LightFit(min_pixels=10 ** 6))
