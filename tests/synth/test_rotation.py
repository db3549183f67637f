"""Ground-truth light rotations of SynthFaces records (synth/rotation.py) against SH rotation."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.lighting import sh
from difareli.data.store import EncodingStore
from difareli.synth import rotation as rot
from difareli.synth.lights import Light, direction


@pytest.fixture(scope="module")
def store(synth_store):
    return EncodingStore.open(synth_store)


def _sunny_record(store) -> str:
    # A record whose light has a sun (so rotating it moves cast shadows).
    for rid in store.ids():
        if rot.record_source(store, rid)[2].has_sun:
            return rid
    pytest.skip("no record with a sun")


def test_rotate_light_is_sh_rotation():
    light = Light("hard", np.random.default_rng(1).normal(0, 0.3, (9, 3)), direction(30, 20), np.array([1.0, 0.9, 0.8]),
                  extra_dirs=np.array([direction(-50, 10)]), extra_rgbs=np.array([[0.2, 0.3, 0.1]]),
                  extra_names=("fill",))
    R = sh.rotation_yaw(73.0) @ sh.rotation_roll(-21.0)
    turned = rot.rotate_light(light, R)
    np.testing.assert_allclose(turned.sh(), sh.rotate(light.sh(), R), atol=2e-6)
    np.testing.assert_allclose(turned.sun_dir, R @ light.sun_dir, atol=1e-12)
    np.testing.assert_allclose(turned.extra_dirs[0], R @ light.extra_dirs[0], atol=1e-12)


def test_rotation_frames_match_the_rotation_videos_lights():
    from types import SimpleNamespace

    from difareli.relight.request import Rotation

    own = np.random.default_rng(2).normal(0, 0.3, (9, 3))
    angles, rots = sh.rotation_frames("roll", 8)
    np.testing.assert_allclose(angles, np.arange(8) * 45.0)
    lights = Rotation("roll", 8).lights(SimpleNamespace(arrays={"light": own}))
    np.testing.assert_allclose(sh.rotate(own, rots), lights, atol=1e-12)
    with pytest.raises(ValueError, match="axis"):
        sh.rotation_frames("pitch", 4)


def test_zero_rotation_reproduces_the_record(store):
    rid = _sunny_record(store)
    gt = rot.ground_truth_rotation(store, rid, "yaw", frames=6)
    rec = store.read(rid)
    assert gt.frames.shape == (6, 32, 32, 3) and gt.frames.dtype == np.uint8
    np.testing.assert_array_equal(gt.frames[0], rec["image"])
    for name in rot.TARGETS:  # the exact encodings of the record itself
        np.testing.assert_array_equal(gt.targets[name][0], rec[f"{name}_gt"])
    assert gt.targets["light"].shape == (6, 9, 3) and gt.targets["shadow"].shape == (6, 1)
    np.testing.assert_allclose(gt.angles, [0, 60, 120, 180, 240, 300])


def test_rotated_frames_follow_sh_rotate(store):
    rid = _sunny_record(store)
    gt = rot.ground_truth_rotation(store, rid, "yaw", frames=4)
    rec = store.read(rid)
    _, rots = sh.rotation_frames("yaw", 4)
    want = sh.rotate(rec["light_gt"], rots)
    np.testing.assert_allclose(gt.targets["light"], want, atol=1e-5)
    # The shading reference follows the rotated SH light on the record's own normals.
    for i in range(4):
        ref = sh.shading_reference(want[i], rec["normal"], mask=np.linalg.norm(rec["normal"], axis=-1) > 0.5)
        np.testing.assert_allclose(gt.targets["shading"][i], ref, atol=1e-4)
    # A moved light changes the image and (for a sunny record) the cast-shadow pattern somewhere.
    assert not np.array_equal(gt.frames[1], gt.frames[0])
    assert gt.cast().shape == (4, 32, 32)


def test_sh_lights_render_without_cast_shadows(store):
    rid = store.ids()[0]
    env = sh.directional_light(np.array([0.0, 0.0, 1.0]), 0.5) + sh.directional_light(np.array([0.0, 1.0, 0.0]), 0.2)
    gt = rot.ground_truth_lights(store, rid, [env])
    np.testing.assert_allclose(gt.targets["light"][0], env, atol=1e-6)
    assert not gt.cast().any()


def test_non_synthfaces_store_is_refused(tmp_path):
    s = EncodingStore.create(tmp_path / "s", {"H": 16, "W": 16, "S": 4, "D": 4}, ["image"], {"generator": "photos"})
    with pytest.raises(ValueError, match="not a SynthFaces store"):
        rot.synth_config(s)
