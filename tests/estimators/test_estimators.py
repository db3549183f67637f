"""Estimators of difareli-preprocess on the two public-domain photos shipped in packages (astronaut, Grace
Hopper). Needs the preprocess extras (mediapipe 0.10.21, face_recognition); skipped without them."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers import HAS_FACE_RECOGNITION, NO_ESTIMATORS

if not HAS_FACE_RECOGNITION:
    pytest.skip(NO_ESTIMATORS, allow_module_level=True)

from difareli.lighting import sh  # noqa: E402
from difareli.data.encodings import PART_INDEX  # noqa: E402
from difareli.estimators import align, geometry, masks  # noqa: E402
from difareli.estimators.identity import DlibIdentity  # noqa: E402
from difareli.estimators.light import SkinSHLight  # noqa: E402
from difareli.lighting.albedo import synthfaces_mean_skin_albedo  # noqa: E402
from difareli.estimators.pipeline import Pipeline  # noqa: E402
from difareli.estimators.shadow import DEFAULT_WEIGHTS, ShadowEstimator  # noqa: E402

S = 256


def astronaut() -> np.ndarray:
    import skimage.data

    return skimage.data.astronaut()


def grace_hopper() -> np.ndarray:
    from matplotlib import cbook
    from PIL import Image

    with cbook.get_sample_data("grace_hopper.jpg") as f:
        return np.asarray(Image.open(f).convert("RGB"))


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    ests = [geometry.FaceMeshGeometry(), masks.FaceMeshSelfieMasks(), SkinSHLight(), DlibIdentity()]
    if DEFAULT_WEIGHTS.is_file():
        ests.append(ShadowEstimator())
    names = None if DEFAULT_WEIGHTS.is_file() else [n for n in
                                                   ("image", "light", "shape", "cam", "identity", "background", "masks",
                                                    "shading", "normal", "depth", "face_mask")]
    return Pipeline(align.FaceAligner(S), ests, names)


@pytest.fixture(scope="module")
def results(pipe):
    return {name: pipe.process(img) for name, img in (("astronaut", astronaut()), ("grace", grace_hopper()))}


def test_tessellation_and_lip_contours():
    from mediapipe.python.solutions.face_mesh_connections import FACEMESH_LIPS

    tris = geometry.tessellation_triangles()
    assert tris.shape == (852, 3) and tris.min() == 0 and tris.max() == 467
    # One consistent winding: every interior edge is used once in each direction.
    directed = {(a, b) for t in tris for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    assert len(directed) == 3 * len(tris)
    lips = {frozenset(e) for e in FACEMESH_LIPS}
    for chain in (masks.LIPS_OUTER_UPPER, masks.LIPS_OUTER_LOWER, masks.LIPS_INNER_UPPER, masks.LIPS_INNER_LOWER):
        assert all(frozenset(p) in lips for p in zip(chain[:-1], chain[1:]))


def test_fit_camera_recovers_a_known_camera(rng):
    v = rng.normal(size=(468, 3))
    cam = geometry.OrthoCamera(0.4, 0.1, -0.2)
    fitted, err = geometry.fit_camera(v, cam.project(v, 200, 200), 200, 200)
    assert np.allclose(fitted.to_array(), [0.4, 0.1, -0.2], atol=1e-6) and err < 1e-6


def test_alignment_is_ffhq_like(results):
    # FFHQ puts the eyes level, 1/4 of the crop apart, centred horizontally.
    _, meta, ctx = results["astronaut"]
    lm = ctx["landmarks"]
    right, left = lm[align.eye_indices("right"), :2].mean(0), lm[align.eye_indices("left"), :2].mean(0)
    assert ctx["image"].shape == (S, S, 3)
    assert abs(np.linalg.norm(left - right) / S - 0.25) < 0.03
    assert abs((left[0] + right[0]) / 2 / S - 0.5) < 0.03 and abs(left[1] - right[1]) < 0.02 * S
    assert right[0] < left[0]  # the subject's right eye is on the image left


def test_landmarks_inside_the_face_box(results):
    # The astronaut's face occupies about x 165-290, y 55-200 of the 512x512 photo.
    _, meta, ctx = results["astronaut"]
    orig = ctx["landmarks"][:, :2] @ np.stack([(np.array(meta["quad"][3]) - meta["quad"][0]) / S,
                                                (np.array(meta["quad"][1]) - meta["quad"][0]) / S]) + meta["quad"][0]
    assert meta["faces"] == 1
    assert orig[:, 0].min() > 150 and orig[:, 0].max() < 300 and orig[:, 1].min() > 40 and orig[:, 1].max() < 215


def test_geometry_conventions(results):
    arrays, meta, ctx = results["astronaut"]
    assert meta["reprojection_px"] < 1e-3
    hit = ctx["gbuffer"].hit
    assert 0.15 < hit.mean() < 0.5
    n = arrays["normal"][hit]
    assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-4) and (n[:, 2] > 0).mean() > 0.97
    # z toward the viewer: the nose tip (landmark 4) is nearer than the cheeks (234, 454).
    depth_at = lambda i: arrays["depth"][int(ctx["landmarks"][i, 1]), int(ctx["landmarks"][i, 0])]  # noqa: E731
    assert depth_at(4) > depth_at(234) + 0.3 and depth_at(4) > depth_at(454) + 0.3
    shape = arrays["shape"].reshape(468, 3)
    assert np.allclose(shape.mean(0), 0, atol=1e-5) and np.isclose(np.sqrt((shape ** 2).sum(1).mean()), 1, atol=1e-5)


@pytest.mark.parametrize("name,max_rel,min_corr", [("astronaut", 0.15, 0.7), ("grace", 0.25, 0.4)])
def test_sh_fit_reproduces_skin_shading(results, name, max_rel, min_corr):
    # Stated error: luminance RMSE of albedo * irradiance vs the photo on the fitted skin pixels is below
    # 15% (astronaut, even studio light) / 25% (Grace Hopper: wrinkles and glasses) of the mean, and the
    # prediction correlates with the photo (the fit explains shading, not just the mean).
    _, meta, _ = results[name]
    fit = meta["light_fit"]
    assert fit["pixels"] > 3000 and fit["rel_rmse"] < max_rel and fit["corr"] > min_corr


def test_sh_fit_recovers_a_rendered_light(results):
    arrays, _, ctx = results["astronaut"]
    est = SkinSHLight(ridge=0.0)
    truth = sh.directional_light([0.5, 0.3, 1.0], [0.9, 0.8, 0.7])
    truth[0] += 0.4  # plus an ambient term
    img = np.clip(est.albedo * sh.irradiance(truth, arrays["normal"].astype(np.float64)), 0, 1)
    mask = est.skin_pixels((img * 255).astype(np.uint8), ctx["gbuffer"], ctx["skin"])
    light, _, stats = est.fit((img * 255).round().astype(np.uint8), arrays["normal"], mask)
    assert stats["rel_rmse"] < 0.01
    assert np.allclose(sh.dominant_direction(light), sh.dominant_direction(truth), atol=0.05)


def test_mirrored_photo_mirrors_the_light(pipe, results):
    # A horizontal flip negates x: band-1 x of the light flips sign, y and z stay.
    light = results["grace"][0]["light"].mean(1)
    flipped = pipe.process(np.ascontiguousarray(grace_hopper()[:, ::-1]))[0]["light"].mean(1)
    assert abs(light[1]) > 0.05
    assert np.allclose(flipped[[1, 2, 3]], light[[1, 2, 3]] * [-1, 1, 1], atol=0.25 * abs(light[1]) + 0.02)


def test_albedo_prior_is_the_synthfaces_mean():
    a = synthfaces_mean_skin_albedo()
    assert a.shape == (3,) and 0.3 < a.mean() < 0.6 and a[0] > a[1] > a[2]


@pytest.mark.parametrize("name", ["astronaut", "grace"])
def test_masks_cover_the_face(results, name):
    arrays, _, ctx = results[name]
    m, lm = arrays["masks"], ctx["landmarks"]
    oval = masks.fill(lm[masks.outline(__import__("mediapipe").solutions.face_mesh.FACEMESH_FACE_OVAL,
                                       lm[:, :2])][:, :2],
                      m.shape)
    assert arrays["face_mask"][oval].mean() > 0.99 and arrays["face_mask"][~oval].mean() < 0.01
    at = lambda i, j=None: m[tuple(np.floor(lm[i, 1::-1] if j is None  # noqa: E731
                                            else (lm[i, 1::-1] + lm[j, 1::-1]) / 2).astype(int))]
    assert at(473) == PART_INDEX["l_eye"] and at(468) == PART_INDEX["r_eye"]  # iris centres
    assert at(50) == PART_INDEX["skin"] and at(280) == PART_INDEX["skin"]     # cheeks
    assert at(4) == PART_INDEX["nose"] and at(0, 13) == PART_INDEX["u_lip"] and at(17, 14) == PART_INDEX["l_lip"]
    # Above the forehead: hair, or for Grace Hopper her Navy cap (a hat); neck under the chin; bottom is clothes.
    assert m[int(lm[10, 1]) - 12, int(lm[10, 0])] == PART_INDEX["hat" if name == "grace" else "hair"]
    assert m[int(lm[152, 1]) + 10, int(lm[152, 0])] == PART_INDEX["neck"]
    assert m[S - 3, S // 2] in (PART_INDEX["clothes"], PART_INDEX["neck"])
    assert arrays["background"][m == PART_INDEX["skin"]].max() == 0



def test_masks_colour_rules_read_only_the_photo(results):
    """The pipeline passes ``inside`` (crop pixels in the photo, not the reflected padding); the colour rules read
    only those: with every pixel inside nothing changes, and rows marked padding get no hat from Grace Hopper's cap."""
    arrays, _, ctx = results["grace"]
    assert ctx["inside"].all()
    without = {k: v for k, v in ctx.items() if k != "inside"}
    np.testing.assert_array_equal(masks.FaceMeshSelfieMasks()(without, {"masks"})["masks"], arrays["masks"])
    cap = np.nonzero((arrays["masks"] == PART_INDEX["hat"]).any(1))[0]
    inside = ctx["inside"].copy()
    inside[:(cap[0] + cap[-1]) // 2] = False  # the cap's top half past the photo's edge
    lab = masks.FaceMeshSelfieMasks()({**ctx, "inside": inside}, {"masks"})["masks"]
    assert (lab[~inside] == PART_INDEX["hat"]).sum() == 0
    assert (lab[inside] == PART_INDEX["hat"]).any()

def test_identity_same_face_close_different_faces_far(pipe, results):
    a = results["astronaut"][0]["identity"]
    g = results["grace"][0]["identity"]
    # A second, differently framed crop of the astronaut: shifted and downscaled input.
    from PIL import Image

    other = np.asarray(Image.fromarray(astronaut()[20:460, 60:500]).resize((300, 300)))
    a2 = pipe.process(other)[0]["identity"]
    assert a.shape == (128,)
    assert np.linalg.norm(a - a2) < 0.6 and np.linalg.norm(a - g) > 0.6


@pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason="shadow classifier weights not trained")
def test_shadow_map_is_cast_times_normalised_c(results):
    from difareli.data.encodings import normalise_c

    for name in ("astronaut", "grace"):
        arrays, meta, ctx = results[name]
        c = float(arrays["shadow"][0])
        assert np.isfinite(c)
        assert np.allclose(arrays["shadow_map"], ctx["cast"] * normalise_c(c), atol=1e-6)
        assert np.isclose(c, meta["shadow_info"]["c"], atol=1e-5) and 0 <= meta["shadow_info"]["p_shadow"] <= 1
        assert not (ctx["cast"] & ~ctx["gbuffer"].hit).any()


def test_identity_equals_face_recognition(results):
    """DlibIdentity calls dlib as face_recognition.face_encodings does, loading only its two models: the same
    descriptor to float precision."""
    import face_recognition

    from difareli.estimators.identity import landmark_box

    for name in ("astronaut", "grace"):
        arrays, _, ctx = results[name]
        box = landmark_box(np.asarray(ctx["landmarks"])[:, :2], ctx["image"].shape[:2])
        ref = face_recognition.face_encodings(np.ascontiguousarray(ctx["image"]), known_face_locations=[box],
                                              num_jitters=1, model="small")[0]
        np.testing.assert_allclose(arrays["identity"], ref, atol=1e-6)


def test_bfm_fit_is_the_same_with_one_blas_thread(results):
    """The pipeline runs the estimators with one BLAS thread (threadpoolctl): the fit does not move."""
    from threadpoolctl import threadpool_limits

    from difareli.estimators.bfm_fit import facemesh_to_68, fit_bfm

    lm = facemesh_to_68(np.asarray(results["astronaut"][2]["landmarks"])[:, :2])
    with threadpool_limits(limits=2, user_api="blas"):
        many = fit_bfm(lm, S, S)
    with threadpool_limits(limits=1, user_api="blas"):
        one = fit_bfm(lm, S, S)
    np.testing.assert_allclose(one.params.shape_vector(), many.params.shape_vector(), atol=1e-6)
    np.testing.assert_allclose(one.cam.to_array(), many.cam.to_array(), atol=1e-7)
    assert one.rmse_px == pytest.approx(many.rmse_px, abs=1e-5)  # px; LAPACK's blocking differs at 1e-7
