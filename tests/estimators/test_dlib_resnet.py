"""The PyTorch port of dlib's face-recognition ResNet (estimators/dlib_resnet.py) against dlib itself, on real
faces: skimage's astronaut (Eileen Collins), matplotlib's Grace Hopper and the astronaut mirrored."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from tests.helpers import HAS_DLIB_MODELS, NO_ESTIMATORS

if not HAS_DLIB_MODELS:
    pytest.skip(NO_ESTIMATORS, allow_module_level=True)

import dlib  # noqa: E402

with warnings.catch_warnings():  # face_recognition_models imports the deprecated pkg_resources
    warnings.simplefilter("ignore")
    import face_recognition_models as frm  # noqa: E402

from difareli.estimators.dlib_resnet import face_descriptors, load, read_dlib_resnet  # noqa: E402
from difareli.estimators.identity import DlibIdentity  # noqa: E402

#: dlib's descriptor in float32 vs ours: measured 2e-7; 1e-5 leaves room for other BLAS / CPU kernels.
TOL = 1e-5


def _images() -> dict[str, np.ndarray]:
    import matplotlib.cbook
    import skimage.data
    from PIL import Image

    astronaut = skimage.data.astronaut()
    with matplotlib.cbook.get_sample_data("grace_hopper.jpg") as f:
        hopper = np.asarray(Image.open(f).convert("RGB"))
    return {"astronaut": astronaut, "hopper": hopper, "mirrored": np.ascontiguousarray(astronaut[:, ::-1])}


@pytest.fixture(scope="module")
def faces(one_thread):
    """name -> (image, the face's dlib rectangle, 5-point shape, 150 px chip, dlib's descriptor of the chip)."""
    detector = dlib.get_frontal_face_detector()
    predictor = dlib.shape_predictor(frm.pose_predictor_five_point_model_location())
    encoder = dlib.face_recognition_model_v1(frm.face_recognition_model_location())
    out = {}
    for name, img in _images().items():
        rect = max(detector(img, 1), key=lambda r: r.area())  # the astronaut's flag patch is a second "face"
        shape = predictor(img, rect)
        chip = dlib.get_face_chip(img, shape, size=150, padding=0.25)
        ref = np.asarray(encoder.compute_face_descriptor(chip), np.float32)
        # the chip path is exactly what compute_face_descriptor(image, shape) does itself
        assert np.array_equal(ref, np.asarray(encoder.compute_face_descriptor(img, shape, 1), np.float32)), name
        out[name] = (img, rect, shape, chip, ref)
    return out


def test_descriptors_match_dlib(faces):
    names = list(faces)
    ours = face_descriptors(np.stack([faces[n][3] for n in names]))
    ref = np.stack([faces[n][4] for n in names])
    assert ours.shape == (3, 128) and ours.dtype == np.float32
    assert np.abs(ours - ref).max() < TOL
    # and they mean what dlib's mean: one person < 0.6 apart (mirrored), two people further
    d = dict(zip(names, ours))
    assert np.linalg.norm(d["astronaut"] - d["mirrored"]) < 0.6 < np.linalg.norm(d["astronaut"] - d["hopper"])
    assert 1.0 < np.linalg.norm(d["hopper"]) < 2.0  # not normalised, as dlib's


def test_batched_equals_one_by_one(faces):
    chips = np.stack([f[3] for f in faces.values()] * 3)  # 9 chips, batches of 4: a ragged last batch
    batched = face_descriptors(chips, batch_size=4)
    single = np.concatenate([face_descriptors(c) for c in chips])
    assert batched.shape == (9, 128)
    np.testing.assert_allclose(batched, single, rtol=0, atol=1e-6)
    np.testing.assert_allclose(batched[:3], batched[3:6], rtol=0, atol=0)


def test_identity_estimator_backends_agree(faces):
    img, rect = faces["hopper"][:2]
    # the estimator boxes FaceMesh landmarks; the detector's corners stand in for them
    lm = np.array([[rect.left(), rect.top()], [rect.right(), rect.bottom()]], np.float32)
    ctx = {"image": img, "landmarks": lm}
    torch_id = DlibIdentity()(ctx, {"identity"})["identity"]
    dlib_id = DlibIdentity(backend="dlib")(ctx, {"identity"})["identity"]
    assert torch_id.shape == (128,) and torch_id.dtype == np.float32
    assert np.abs(torch_id - dlib_id).max() < TOL
    assert np.linalg.norm(torch_id - faces["hopper"][4]) < 0.3  # the same face, from a slightly different box
    assert DlibIdentity(num_jitters=4).backend == "dlib"  # dlib's jitter is not ported
    with pytest.raises(ValueError, match="backend"):
        DlibIdentity(backend="onnx")


def test_reader_parses_the_whole_file():
    parsed = read_dlib_resnet(frm.face_recognition_model_location())
    kinds = [k for k, _ in parsed["layers"]]
    assert kinds.count("con") == 29 and kinds.count("affine") == 29 and kinds[-2:] == ["avg_pool", "fc"]
    np.testing.assert_allclose(parsed["mean_rgb"], [122.782, 117.001, 104.298], rtol=1e-6)
    assert load() is load()  # parsed once per process


def test_corrupt_file_is_refused_by_name(tmp_path):
    data = open(frm.face_recognition_model_location(), "rb").read()
    truncated = tmp_path / "truncated.dat"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="truncated.dat.*file ends early"):
        read_dlib_resnet(truncated)
    wrong = tmp_path / "wrong.dat"
    wrong.write_bytes(open(frm.pose_predictor_five_point_model_location(), "rb").read())  # another dlib file
    with pytest.raises(ValueError, match="wrong.dat.*not a readable dlib face-recognition ResNet"):
        read_dlib_resnet(wrong)
    with pytest.raises(ValueError, match="missing.dat"):
        read_dlib_resnet(tmp_path / "missing.dat")
