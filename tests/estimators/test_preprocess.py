"""difareli-preprocess end to end: bad inputs, the report, exit status, resume (also after a killed run)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from difareli.estimators.loading import BadInput, load_image, record_ids, sanitise_id

from tests.helpers import HAS_FACE_RECOGNITION, NO_ESTIMATORS

REPO = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------ loading (no mediapipe needed)
def test_load_conversions_and_rejections(tmp_path):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (80, 90, 3), dtype=np.uint8)
    Image.fromarray(rgb[..., 0]).save(tmp_path / "grey.png")
    arr, notes = load_image(tmp_path / "grey.png")
    assert arr.shape == (80, 90, 3) and np.array_equal(arr[..., 2], rgb[..., 0]) and "grayscale" in notes[0]

    rgba = np.concatenate([rgb, np.full((80, 90, 1), 0, np.uint8)], axis=-1)
    rgba[:40, :, 3] = 255
    Image.fromarray(rgba).save(tmp_path / "alpha.png")
    arr, notes = load_image(tmp_path / "alpha.png")
    assert np.array_equal(arr[:40], rgb[:40]) and (arr[40:] == 128).all() and "alpha" in notes[0]

    deep = (np.arange(80 * 90).reshape(80, 90) * 9).astype(np.uint16)
    Image.fromarray(deep).save(tmp_path / "deep.png")
    arr, notes = load_image(tmp_path / "deep.png")
    assert np.array_equal(arr[..., 1], np.round(deep / 65535 * 255)) and "16-bit" in notes[0]

    Image.fromarray(rgb[:40, :40]).save(tmp_path / "tiny.png")
    Image.fromarray(np.zeros((64, 8200), np.uint8)).save(tmp_path / "huge.png")
    (tmp_path / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg" * 10)
    (tmp_path / "notes.txt").write_text("hello")
    for name, reason in (("tiny.png", "too small"), ("huge.png", "too large"), ("broken.jpg", "unreadable"),
                         ("notes.txt", "not an image")):
        with pytest.raises(BadInput, match=reason):
            load_image(tmp_path / name)


def test_record_ids_are_sanitised_and_unique():
    assert sanitise_id("my photo (1)") == "my_photo__1_" and sanitise_id("..x") == "x"
    ids = record_ids([Path("a/b c.jpg"), Path("a/b c.png"), Path("a/.z/-q.jpg")])
    assert ids == {Path("a/b c.jpg"): "b_c.jpg", Path("a/b c.png"): "b_c.png", Path("a/.z/-q.jpg"): "q"}


# ------------------------------------------------------------------ the pipeline (mediapipe needed)
if not HAS_FACE_RECOGNITION:
    pytest.skip(NO_ESTIMATORS, allow_module_level=True)


def _photos(folder: Path) -> None:
    import skimage.data
    from matplotlib import cbook

    folder.mkdir(parents=True, exist_ok=True)
    Image.fromarray(skimage.data.astronaut()).save(folder / "astronaut.png")
    with cbook.get_sample_data("grace_hopper.jpg") as f:
        (folder / "grace hopper.jpg").write_bytes(f.read())


def _bad_files(folder: Path) -> dict[str, str]:
    rng = np.random.default_rng(1)
    Image.fromarray(rng.integers(0, 256, (40, 40, 3), dtype=np.uint8)).save(folder / "tiny.png")
    Image.fromarray(np.zeros((64, 8200), np.uint8)).save(folder / "huge.png")
    (folder / "broken.jpg").write_bytes(b"\xff\xd8 truncated" * 50)
    (folder / "notes.txt").write_text("not a photo")
    ramp = np.linspace(0, 255, 256)[None, :, None] * np.ones((256, 1, 3))
    Image.fromarray(ramp.astype(np.uint8)).save(folder / "noface.png")
    return {"tiny.png": "too small", "huge.png": "too large", "broken.jpg": "unreadable",
            "notes.txt": "not an image", "noface.png": "no face"}


def _cli(*overrides: str, **kw) -> subprocess.Popen:
    env = dict(os.environ, PYTHONWARNINGS="ignore", GLOG_minloglevel="2", TF_CPP_MIN_LOG_LEVEL="2")
    return subprocess.Popen([sys.executable, "-m", "difareli.cli.preprocess", *overrides, "progress=false"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)


def test_cli_two_photos_plus_bad_files_then_rerun_does_nothing(tmp_path):
    from difareli.data.encodings import ENCODINGS
    from difareli.data.store import EncodingStore

    src, out = tmp_path / "in", tmp_path / "out"
    _photos(src)
    bad = _bad_files(src)
    proc = _cli(f"in_dir={src}", f"out_dir={out}")
    log = proc.communicate(timeout=300)[0]
    assert proc.returncode == 1, log  # some inputs failed
    store = EncodingStore.open(out)
    assert store.ids() == ["astronaut", "grace_hopper"]
    assert store.verify(check_values=True) == []
    # Every encoding a photo can give: all of the schema but the synthetic ground truth (*_gt).
    assert set(store.encodings) == {n for n, e in ENCODINGS.items() if not e.oracle}
    rec = store.read("grace_hopper")
    assert (rec["image"].shape == (256, 256, 3) and rec["identity"].shape == (128,)
            and rec["shape"].shape == (53,))  # BFM fit: the SynthFaces layout
    report = json.loads((out / "preprocess_report.json").read_text())
    by_file = {Path(e["file"]).name: e for e in report["images"]}
    assert report["written"] == 2 and report["failed"] == len(bad)
    # Per-stage times in the report and on the console: alignment, then every estimator that ran.
    stages = report["stage_ms_per_image"]
    assert list(stages)[:2] == ["align", "BFMGeometry"] and {"DlibIdentity", "ShadowEstimator"} <= set(stages)
    assert all(v > 0 for v in stages.values()) and "per image: align " in log
    for name, reason in bad.items():
        assert by_file[name]["status"] == "failed" and reason in by_file[name]["reason"], by_file[name]
    assert {p.name for p in (out / "previews").iterdir()} == {"astronaut.png", "grace_hopper.png"}
    assert Image.open(out / "previews" / "astronaut.png").size == (5 * 256 + 4 * 2, 256)
    mtimes = {p: p.stat().st_mtime_ns for p in (out / "records").rglob("*")}

    # Re-run in-process (same config, no second interpreter start-up): nothing is recomputed or rewritten.
    from hydra import compose, initialize_config_dir

    from difareli.cli.preprocess import build_pipeline
    from difareli.configs import CONFIG_DIR
    from difareli.estimators.batch import run

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("preprocess", overrides=[f"in_dir={src}", f"out_dir={out}"])
    summary = run(build_pipeline(cfg), str(src), str(out), progress=False)
    report = json.loads((out / "preprocess_report.json").read_text())
    assert summary.written == 0 and report["skipped"] == 2 and report["failed"] == len(bad)
    assert {p: p.stat().st_mtime_ns for p in (out / "records").rglob("*")} == mtimes

    # A word for a boolean is refused before anything loads (bool("no") is True: it would have overwritten).
    proc = _cli(f"in_dir={src}", f"out_dir={out}", "overwrite=no")
    log = proc.communicate(timeout=120)[0]
    assert proc.returncode == 2 and "overwrite='no' is invalid: give overwrite=true or overwrite=false" in log, log
    assert {p: p.stat().st_mtime_ns for p in (out / "records").rglob("*")} == mtimes


def test_several_faces_keep_the_largest():
    import skimage.data
    from matplotlib import cbook

    from difareli.estimators.align import FaceAligner

    with cbook.get_sample_data("grace_hopper.jpg") as f:
        grace = np.asarray(Image.open(f).convert("RGB").resize((300, 256)))
    canvas = np.full((512, 812, 3), 200, np.uint8)
    canvas[:, :512] = skimage.data.astronaut()
    canvas[100:356, 512:] = grace
    res = FaceAligner(128)(canvas)
    assert res["faces"] == 2 and "kept the largest" in res["notes"][0]
    assert np.mean(res["quad"], axis=0)[0] < 512  # the astronaut (larger face), not Grace Hopper


@pytest.mark.slow  # two interpreter start-ups (~20 s on 2 busy cores)
def test_resume_after_a_killed_run(tmp_path):
    from difareli.data.store import EncodingStore

    src, out = tmp_path / "in", tmp_path / "out"
    _photos(src)
    astro = np.asarray(Image.open(src / "astronaut.png"))
    for i in range(3):  # more work, so that the kill lands between records
        Image.fromarray(np.ascontiguousarray(np.roll(astro, 8 * (i + 1), axis=1))).save(src / f"shifted{i}.png")
    args = (f"in_dir={src}", f"out_dir={out}", "encodings=[image,normal,depth,cam]", "previews=false")
    proc = _cli(*args, start_new_session=True)
    records = out / "records"
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if records.is_dir() and len([p for p in records.iterdir() if not p.name.startswith(".")]) >= 1:
            break
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate()
    done_before = {p.name for p in records.iterdir() if not p.name.startswith(".")}
    assert 1 <= len(done_before) <= 5

    proc = _cli(*args)
    log = proc.communicate(timeout=300)[0]
    assert proc.returncode == 0, log
    store = EncodingStore.open(out)
    assert len(store) == 5 and store.verify(check_values=True) == []
    assert not [p for p in records.iterdir() if p.name.startswith(".")]
    report = json.loads((out / "preprocess_report.json").read_text())
    assert report["skipped"] == len(done_before) and report["written"] == 5 - len(done_before)


@pytest.mark.slow  # two spawned workers start mediapipe and dlib (~20 s on 2 busy cores)
def test_workers_write_the_same_records(tmp_path):
    """workers=2: the estimators in two processes, the store written here; every encoding as in one process."""
    from hydra import compose, initialize_config_dir

    from difareli.cli.preprocess import build_pipeline
    from difareli.configs import CONFIG_DIR
    from difareli.estimators.batch import run
    from difareli.data.store import EncodingStore

    src = tmp_path / "in"
    _photos(src)
    (src / "notes.txt").write_text("not a photo")
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        names = "[image,shape,cam,normal,masks,light,identity,shadow_map]"
        cfg = compose("preprocess", overrides=[f"in_dir={src}", "out_dir=x", f"encodings={names}"])
    pipe = build_pipeline(cfg)
    one = run(pipe, str(src), str(tmp_path / "one"), previews=False, progress=False)
    two = run(pipe, str(src), str(tmp_path / "two"), previews=True, progress=False, workers=2)
    assert (one.written, one.failed) == (two.written, two.failed) == (2, 1)
    a, b = EncodingStore.open(tmp_path / "one"), EncodingStore.open(tmp_path / "two")
    assert a.ids() == b.ids() == ["astronaut", "grace_hopper"]
    for rid in a.ids():
        ra, rb = a.read(rid), b.read(rid)
        for name in ra:
            np.testing.assert_allclose(np.asarray(rb[name], np.float64), np.asarray(ra[name], np.float64),
                                       atol=1e-5, err_msg=f"{rid}/{name}")
    assert (tmp_path / "two" / "previews" / "astronaut.png").is_file()
    assert set(two.stage_ms()) == set(one.stage_ms())
