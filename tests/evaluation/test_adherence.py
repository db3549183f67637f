"""The per-image metrics against closed forms: lighting error, shadow darkening / adherence / IoU, identity."""

import math

import numpy as np
import pytest

from difareli.evaluation import adherence
from difareli.lighting import sh


def _rot_y(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


@pytest.mark.parametrize("deg", [0.0, 17.0, 45.0, 120.0])
def test_light_rotated_by_a_known_angle_gives_that_angle(deg):
    d = np.array([0.6, 0.0, 0.8])  # perpendicular to the rotation axis: turned by exactly deg
    light = sh.directional_light(d, np.array([0.9, 0.8, 0.7])) + 0.3 * sh.directional_light(np.array([0, 0, 1.0]), 1)
    rotated = sh.rotate(light, _rot_y(deg))
    angle, rel = adherence.light_error(rotated, light)
    # the dominant direction of the sum (sun + frontal fill) turns with the environment: angle(l, R l) = deg
    assert angle == pytest.approx(deg, abs=1e-6)
    tilted = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])  # off the plane: acos(d . R d)
    one = sh.directional_light(tilted, 1.0)
    want = math.degrees(math.acos(float(tilted @ _rot_y(deg) @ tilted)))
    assert adherence.light_error(sh.rotate(one, _rot_y(deg)), one)[0] == pytest.approx(want, abs=1e-6)
    # band 0 is rotation-invariant, bands 1-2 rotate: the relative error grows with the angle, 0 at 0
    assert (rel == pytest.approx(0, abs=1e-12)) if deg == 0 else rel > 0
    assert adherence.light_error(2 * light, light) == (pytest.approx(0, abs=1e-6), pytest.approx(1.0))


def _face(h=40, w=40):
    face = np.zeros((h, w), bool)
    face[5:35, 8:32] = True
    m = np.zeros((h, w), bool)
    m[5:20, 8:20] = True  # 180 of the face's 720 pixels: a quarter
    return face, m


@pytest.mark.parametrize("x", [0.1, 0.3])
def test_darkening_by_exactly_x_inside_m(x):
    face, m = _face()
    img = np.full((40, 40, 3), 200, np.uint8)
    dark = img.copy()
    dark[m] = round(200 - 255 * x)  # grey: luminance = value / 255
    assert adherence.darkening(dark, face, m) == pytest.approx((200 - round(200 - 255 * x)) / 255, abs=1e-12)
    assert adherence.shadow_share(face, m) == 0.25
    s = adherence.shadow_scores(dark, dark, face, m)  # the relit image equals the ground truth: a perfect relight
    assert s["shadow_adherence"] == 1.0 and s["shadow_darkening"] == pytest.approx(x, abs=0.5 / 255)
    # darker than 0.75 x the face's median (200) exactly inside M: the detector finds M
    assert s["shadow_iou"] == (1.0 if x > 0.25 * 200 / 255 else 0.0)
    half = img.copy()
    half[m] = round(200 - 255 * x / 2)
    assert adherence.shadow_scores(half, dark, face, m)["shadow_adherence"] == pytest.approx(0.5, abs=0.01)
    # no shadow in the relit image: adherence 0
    assert adherence.shadow_scores(img, dark, face, m)["shadow_adherence"] == pytest.approx(0.0, abs=1e-12)


def test_shadow_metrics_undefined_on_a_tiny_or_whole_face_shadow():
    face, _ = _face()
    img = np.full((40, 40, 3), 120, np.uint8)
    tiny = np.zeros_like(face)
    tiny[5:7, 8:10] = True  # 4 px of 720
    assert all(math.isnan(v) for v in adherence.shadow_scores(img, img, face, tiny).values())
    assert all(math.isnan(v) for v in adherence.shadow_scores(img, img, face, face).values())
    flat = adherence.shadow_scores(img, img, face, _face()[1])  # a ground truth without a visible shadow
    assert math.isnan(flat["shadow_adherence"]) and flat["shadow_darkening"] == 0.0


def test_detector_is_relative_to_the_face_median():
    face, m = _face()
    for level in (60, 200):  # the same relative drop at two exposures is the same shadow
        img = np.full((40, 40, 3), level, np.uint8)
        img[m] = round(level * 0.6)
        assert np.array_equal(adherence.detect_shadow(img, face), m)


def test_relit_image_equal_to_the_target_rendering(synth_store):
    """Relit = the target's own image on its geometry: lighting error 0, adherence 1."""
    from difareli.data.store import EncodingStore
    from difareli.lighting.light_fit import LightFit

    store = EncodingStore.open(synth_store)
    rid = store.ids()[0]
    arrays = store.read(rid, ["image", "normal", "face_mask", "masks"])
    target = LightFit()(arrays)
    angle, rel = adherence.relit_light_error(arrays["image"], arrays, target)
    assert angle == pytest.approx(0, abs=1e-5) and rel == pytest.approx(0, abs=1e-12)


def test_identity_cosine(synth_store):
    from difareli.evaluation import identity

    if identity.unavailable():
        pytest.skip(identity.unavailable())
    from difareli.data.store import EncodingStore

    store = EncodingStore.open(synth_store)
    a = store.read(store.ids()[0], ["image", "face_mask"])
    sims = identity.similarities(a["image"], a["face_mask"], {"self": (a["image"], a["face_mask"])})
    assert sims["self"] == pytest.approx(1.0, abs=1e-6)
    assert identity.cosine([1, 0], [0, 2]) == 0.0 and identity.cosine([1, 2], [2, 4]) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="empty face mask"):
        identity.face_box(np.zeros((4, 4), bool))


def test_identity_same_subject_scores_higher(synth_store):
    """On the session's store (8 subjects x 2 lights, 32 px): same-subject pairs have a higher mean cosine than
    different-subject ones (each face upsampled to a 150 px chip)."""
    from difareli.evaluation import identity

    if identity.unavailable():
        pytest.skip(identity.unavailable())
    from difareli.data.store import EncodingStore

    store = EncodingStore.open(synth_store)
    ids = store.ids()
    arr = [store.read(r, ["image", "face_mask"]) for r in ids]
    d = identity.descriptors([a["image"] for a in arr], [a["face_mask"] for a in arr])
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    subj = np.array([store.meta(r)["subject"] for r in ids])
    same, off = subj[:, None] == subj[None], ~np.eye(len(ids), dtype=bool)
    c = d @ d.T
    assert c[same & off].mean() > c[~same].mean() + 0.01
