"""The CLI's named targets, the app's presets (one home, lighting.presets): target.light=<direction or HDR map>,
target.pitch, target.envmap=<HDR map name>, refused in one line when they name nothing; difareli-benchmark
checkpoint=; a comparison.png in which a face is readable."""

from __future__ import annotations

import subprocess
import sys
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.errors import UserError
from difareli.lighting import sh
from difareli.lighting.presets import DIRECTIONS, preset_light
from difareli.relight.request import Request, Target
from tests.helpers import compose_train

OWN = sh.directional_light([0.0, 0.0, 1.0], 1.0)
OWN[0] += 1.0


def light_of(target: Target) -> np.ndarray:
    return target.for_source(None, SimpleNamespace(arrays={"light": OWN}, what="a face", photo=None))[0].lights[0]


def test_named_lights_pitch_and_envmap_names_are_the_apps():
    for name, (direction, _) in DIRECTIONS.items():
        np.testing.assert_allclose(sh.dominant_direction(light_of(Target(light=name))),
                                   np.asarray(direction) / np.linalg.norm(direction), atol=1e-6)
    np.testing.assert_allclose(light_of(Target(light="studio")), preset_light("studio", OWN))
    np.testing.assert_allclose(light_of(Target(envmap="studio", yaw=30.0)), preset_light("studio", OWN, yaw=30.0))
    up = sh.dominant_direction(light_of(Target(pitch=30.0, sun="peak")))
    np.testing.assert_allclose(up, [0.0, np.sin(np.radians(30)), np.cos(np.radians(30))], atol=1e-6)


def relight_cfg(tmp_path, *over):
    return compose_train(tmp_path, ["checkpoint=difareli_pp_ss-synth64", f"image={tmp_path / 'p.png'}", *over],
                         config_name="relight")


def test_the_relight_config_takes_them_and_refuses_a_name_it_lacks_in_one_line(tmp_path):
    iio.imwrite(tmp_path / "p.png", np.zeros((64, 64, 3), np.uint8))
    assert Request.from_config(relight_cfg(tmp_path, "target.light=top")).target == Target(light="top")
    assert Request.from_config(relight_cfg(tmp_path, "target.pitch=30")).target == Target(pitch=30)
    assert Request.from_config(relight_cfg(tmp_path, "target.envmap=studio", "target.yaw=90")).target == \
        Target(envmap="studio", yaw=90)
    with pytest.raises(UserError, match=r"^target.light=sideways: no such named light or file; give one of left, "
                                        r"right, top, rim, front, sunset, studio, overcast, window, or a 9x3 SH"):
        Request.from_config(relight_cfg(tmp_path, "target.light=sideways"))
    with pytest.raises(UserError, match=r"^target.envmap=top: no such named light or file; give one of sunset"):
        Request.from_config(relight_cfg(tmp_path, "target.envmap=top"))
    with pytest.raises(UserError, match="target.light and target.pitch: give exactly one target"):
        Request.from_config(relight_cfg(tmp_path, "target.light=top", "target.pitch=10"))
    cmd = [sys.executable, "-m", "difareli.cli.relight", "checkpoint=difareli_pp_ss-synth64",
           f"image={tmp_path / 'p.png'}", "target.light=sideways", f"out_dir={tmp_path / 'o'}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert len([line for line in done.stderr.splitlines() if line.strip()]) <= 2, done.stderr


def test_benchmark_checkpoint_is_method_checkpoint(synth_store, tmp_path):
    from difareli.cli.benchmark import run

    base = [f"store={synth_store}", "limit=1", "progress=false", "num_threads=null", "save_images=false",
            "protocols=[same_subject]", "runtime.device=cpu"]
    res = run(compose_train(tmp_path / "a", [*base, "checkpoint=difareli_pp_ss-synth64"], config_name="benchmark"))
    assert [r.method for r in res.records] == ["student"] and len(res.records) == 1
    said = run(compose_train(tmp_path / "b", [*base, "method=diffusion", "checkpoint=difareli_pp_ss-synth64"],
                             config_name="benchmark"))
    assert [(r.method, r.dssim) for r in said.records] == [(r.method, r.dssim) for r in res.records]
    with pytest.raises(UserError, match=r"checkpoint=difareli_pp_ss-synth64 relights with method=diffusion, and "
                                        r"method=lambertian was given too; drop one of them"):
        run(compose_train(tmp_path / "c", [*base, "method=lambertian", "checkpoint=difareli_pp_ss-synth64"],
                          config_name="benchmark"))
    with pytest.raises(UserError, match="name two checkpoints; give one of them"):
        run(compose_train(tmp_path / "d", [*base, "method=diffusion", "method.checkpoint=difareli-synth64",
                                           "checkpoint=difareli_pp_ss-synth64"], config_name="benchmark"))


def test_a_comparison_shows_a_face_at_least_256_px_tall(synth_store, tmp_path):
    from difareli.cli.relight import run

    written = run(compose_train(tmp_path, ["checkpoint=difareli_pp_ss-synth64", f"store={synth_store}",
                                           "target.yaw=45", "progress=false", "runtime.device=cpu"],
                                config_name="relight"))
    relit, comparison = iio.imread(written["image"]), iio.imread(written["comparison"])
    assert relit.shape[0] == 32 and comparison.shape[:2] == (comparison.shape[0], 2 + 2 * (256 + 2))
    cell = comparison[-2 - 256:-2, 2 + 256 + 2:2 + 2 * 256 + 2]  # the relit face, 8x, below the labels
    np.testing.assert_array_equal(cell[::8, ::8], relit)
    np.testing.assert_array_equal(cell, np.repeat(np.repeat(relit, 8, axis=0), 8, axis=1))


def test_a_photo_under_a_new_light_gets_the_photo_default_shadow_unless_its_own_is_stronger():
    from difareli.data.encodings import denormalise_c
    from difareli.data.target_shadow import PHOTO_SHADOW, photo_shadow
    from difareli.relight.request import rotation_targets

    default = denormalise_c(PHOTO_SHADOW)
    frontal = -4.122039794921875  # the frontal photo: its own c drew no nose shadow
    assert photo_shadow(frontal)[0] == default and "default strength" in photo_shadow(frontal)[1]
    assert photo_shadow(default + 0.0)[0] == default and photo_shadow(None)[0] == default
    arrays = {"light": OWN, "shadow": np.array([frontal], np.float32)}
    photo = SimpleNamespace(arrays=arrays, what="a photo", photo=object())
    record = SimpleNamespace(arrays=arrays, what="a record", photo=None)
    shadow_of = lambda t, s: t.for_source(None, s)[0].shadows[0]  # noqa: E731
    assert shadow_of(Target(light="left", sun="peak"), photo) == pytest.approx(default)
    assert shadow_of(Target(light="left", shadow=-3.0), photo) == -3.0  # a given strength stays
    assert shadow_of(Target(), photo) is None  # its own light: the reconstruction keeps its own c
    assert shadow_of(Target(light="left"), record) is None  # a store record keeps its policy (its own c)
    targets, why = rotation_targets(arrays, "yaw", 4)
    assert targets.shadows == (pytest.approx(default),) * 4 and "default strength" in why
