"""difareli-relight through the real Hydra config: relit image, comparison with ground truth, rotation videos,
and clear errors for bad inputs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.utils.viz import video_format

from difareli.lighting import sh
from difareli.cli.relight import run
from difareli.relight.relighter import Relighter
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets
from difareli.render import sun_fit

from tests.helpers import compose_train

pytestmark = pytest.mark.usefixtures("one_thread")

CELL = 32 + 2  # a 32 px image plus the grid's 2 px padding
BIG = 8 * 32 + 2  # in comparison.png: shown 8x (a face at least 256 px tall), plus the padding


def big(image):
    return np.repeat(np.repeat(np.asarray(image), 8, axis=0), 8, axis=1)


def compose(out: Path, overrides: list[str]):
    return compose_train(out, [*overrides, "progress=false", "runtime.device=cpu"], config_name="relight")


@pytest.fixture(scope="module")
def ckpt(tiny_checkpoint) -> Path:
    return tiny_checkpoint("difareli_pp")


def test_yaw_target_writes_relit_and_comparison(ckpt, depth_store, tmp_path):
    cfg = compose(tmp_path, [f"checkpoint={ckpt}", f"store={depth_store}", "target.yaw=60", "sampler=unipc",
                             "sampler.steps=20"])
    written = run(cfg)
    relit, comparison = iio.imread(written["image"]), iio.imread(written["comparison"])
    assert written["image"] == tmp_path / "relit.png" and relit.shape == (32, 32, 3)
    assert comparison.shape[1:] == (2 * BIG + 2, 3) and comparison.shape[0] > BIG + 2  # a header, input | relit
    store = EncodingStore.open(depth_store)
    rid = store.ids(split="test")[0]  # record=null: the first test record
    np.testing.assert_array_equal(comparison[-258:-2, 2:258], big(store.read(rid, ["image"])["image"]))
    np.testing.assert_array_equal(comparison[-258:-2, 2 + BIG:258 + BIG], big(relit))
    # The same relight through the API: UniPC-20 under the input's light rotated 60 degrees about +y, its map
    # marched toward the input light's key sun found from the input's cast shadows, turned with it.
    r = Relighter(cfg.checkpoint, cfg.sampler, device="cpu")
    own = np.asarray(store.read(rid, ["light"])["light"])
    sun = sh.rotation_yaw(60.0) @ sun_fit.record_sun(store, rid, own).direction
    source = r.source(store, rid)  # holds the face mask the key sun is found on, beside the model's inputs
    assert "face_mask" in source.arrays and "face_mask" not in r.needed_encodings()
    np.testing.assert_array_equal(r.key_sun(source).direction, sun_fit.record_sun(store, rid, own).direction)
    np.testing.assert_array_equal(r.relight(r.source(store, rid), Targets.of([sh.yaw(own, 60.0)], suns=[sun]))[0],
                                  relit)
    # target.sun=peak: toward the turned light's radiance peak.
    peak = run(compose(tmp_path / "peak", [f"checkpoint={ckpt}", f"store={depth_store}", "target.yaw=60",
                                           "sampler=unipc", "sampler.steps=20", "target.sun=peak"]))
    np.testing.assert_array_equal(r.relight(r.source(store, rid), Targets.of([sh.yaw(own, 60.0)]))[0],
                                  iio.imread(peak["image"]))


@pytest.mark.parametrize("target,gt", [("s00006_l1", True), ("s00000_l1", False)])
def test_target_record_shows_ground_truth_for_same_subject(target, gt, ckpt, depth_store, tmp_path):
    cfg = compose(tmp_path, [f"checkpoint={ckpt}", f"store={depth_store}", "record=s00006_l0",
                             f"target.record={target}", "sampler.steps=5"])
    comparison = iio.imread(run(cfg)["comparison"])
    assert comparison.shape[1] == (3 if gt else 2) * BIG + 2
    if gt:
        truth = EncodingStore.open(depth_store).read(target, ["image"])["image"]
        np.testing.assert_array_equal(comparison[-258:-2, 2 + 2 * BIG:258 + 2 * BIG], big(truth))


def test_rotation_video_gif_and_contact_sheet(ckpt, depth_store, tmp_path):
    cfg = compose(tmp_path, [f"checkpoint={ckpt}", f"store={depth_store}", "video.axis=yaw", "video.frames=12",
                             "sampler.steps=5"])
    written = run(cfg)
    # format=auto: MP4 where imageio's ffmpeg plugin is installed, else GIF
    assert set(written) == {"video", "sheet"} and written["video"].suffix == f".{video_format()}"
    frames = iio.imread(written["video"], index=None)
    assert frames.shape[0] == 12 and frames.shape[1:3] == (32, 32)
    assert len({f.tobytes() for f in frames}) > 1  # the light moves
    sheet = iio.imread(written["sheet"])
    assert sheet.shape == (2 * (CELL + 14) + 2, 10 * CELL + 2, 3)  # 10 captioned frames per row: 10 + 2


def test_two_targets_is_an_error(ckpt, depth_store, tmp_path):
    cfg = compose(tmp_path, [f"checkpoint={ckpt}", f"store={depth_store}", "target.yaw=60", "target.roll=30"])
    with pytest.raises(ValueError, match="exactly one target") as e:
        run(cfg)
    assert "roll" in str(e.value) and "yaw" in str(e.value)
    assert not (tmp_path / "relit.png").exists()


def test_no_target_is_an_error(ckpt, depth_store, tmp_path):
    cfg = compose(tmp_path, [f"checkpoint={ckpt}", f"store={depth_store}"])
    with pytest.raises(ValueError, match="give a target") as e:
        run(cfg)
    assert "video.axis" in str(e.value)


def test_missing_files_are_named(ckpt, depth_store, tmp_path):
    missing = tmp_path / "nope" / "last.ckpt"
    with pytest.raises(FileNotFoundError, match=str(missing)):
        run(compose(tmp_path, [f"checkpoint={missing}", f"store={depth_store}", "target.yaw=60"]))
    light = tmp_path / "light.npy"
    with pytest.raises(FileNotFoundError, match=str(light)):
        run(compose(tmp_path, [f"checkpoint={ckpt}", f"store={depth_store}", f"target.light={light}"]))
    with pytest.raises(FileNotFoundError, match=str(tmp_path / "no_store")):
        run(compose(tmp_path, [f"checkpoint={ckpt}", f"store={tmp_path / 'no_store'}", "target.yaw=60"]))


def test_missing_depth_names_encoding_and_store(ckpt, synth_store, tmp_path):
    # DiFaReli++'s target shadow maps are ray-marched on the depth: a store without it fails up front.
    src = EncodingStore.open(synth_store)
    keep = [n for n in src.encodings if n != "depth"]
    dst = EncodingStore.create(tmp_path / "nodepth", src.dims, keep, src.store_meta)
    dst.write("s00006_l0", {k: np.asarray(v) for k, v in src.read("s00006_l0", keep).items()}, src.meta("s00006_l0"))
    with pytest.raises(KeyError, match="depth") as e:
        run(compose(tmp_path, [f"checkpoint={ckpt}", f"store={dst.root}", "target.yaw=60"]))
    assert str(dst.root) in str(e.value)


@pytest.mark.slow
def test_console_script(ckpt, depth_store, tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    exe = Path(sys.executable).with_name("difareli-relight")
    subprocess.run([str(exe), f"checkpoint={ckpt}", f"store={depth_store}", "target.yaw=60", "sampler=unipc",
                    "sampler.steps=5", "progress=false", f"hydra.run.dir={tmp_path}"], check=True, env=env,
                   cwd=tmp_path)
    assert iio.imread(tmp_path / "relit.png").shape == (32, 32, 3)
