"""difareli-demo (the README's main job) at toy size, and relighting a photo (difareli-relight image=...)."""

from __future__ import annotations

import warnings

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.checkpoints import zoo
from difareli.errors import UserError

from tests.helpers import HAS_ESTIMATORS, compose_train

pytestmark = pytest.mark.usefixtures("one_thread")


def test_demo_writes_grid_video_and_table(tiny_checkpoint, tmp_path, capsys):
    from difareli.cli.demo import run

    ckpt = tiny_checkpoint("difareli_pp")  # 32 px
    cfg = compose_train(tmp_path, [f"checkpoint={ckpt}", "resolution=32", "subjects=10", "frames=4", "pairs=2",
                                   "rows=1", "photo=false", "progress=false", "sampler.steps=3",
                                   "runtime.device=cpu"], config_name="demo")
    capsys.readouterr()  # the tiny checkpoint's own training log
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run(cfg)
    # No warning about the lights the demo chose itself (its rotation's frames).
    assert not [w for w in caught if "irradiance" in str(w.message)]
    # The answer first, short: what was relit, by which model, where the files are.
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "== difareli-demo: the answer ==" and out.index("== the detail ==") <= 6
    assert out[1].startswith("relit: 1 unseen SynthFaces subjects") and out[2].startswith(f"model: {ckpt}")
    assert out[3].startswith(f"files in {tmp_path.resolve()}") and "comparison.png (input | relit" in out[3]
    grid = iio.imread(res.paths["comparison"])
    assert grid.shape == (96 + 4 + 18 + 14, 3 * 98 + 2, 3)  # header, one captioned row x3: input | relit | ground truth
    frames = iio.imread(res.paths["video"])
    assert frames.shape[0] == 4 and np.ptp(frames.astype(int), axis=0).max() > 0  # the light moves
    methods = res.table.methods
    assert methods[:2] == ["identity", "lambertian"] and methods[2].startswith("difareli_pp/unipc-3")
    assert set(res.table.protocols) == {"same", "different"}
    for m in methods:
        for p in res.table.protocols:
            assert res.table.cells[(m, p)]["dssim"].n == 2
    assert (tmp_path / "benchmark.md").read_text().startswith("|")
    assert any("shadow strength" in n for n in res.notes)


def test_demo_refuses_an_unknown_checkpoint_name(tmp_path):
    from difareli.cli.demo import run

    cfg = compose_train(tmp_path, ["checkpoint=not-a-model"], config_name="demo")
    with pytest.raises(FileNotFoundError, match="shipped checkpoint"):
        run(cfg)


def test_demo_checks_its_runtime_before_any_work(tmp_path):
    from difareli.cli.demo import run

    cfg = compose_train(tmp_path, ["runtime.precision=fp8", f"out_dir={tmp_path / 'out'}"], config_name="demo")
    with pytest.raises(UserError, match="runtime.precision='fp8' is not one of"):
        run(cfg)
    assert not (tmp_path / "out").exists()  # no store made, nothing written


def test_relight_image_without_estimators_says_how_to_install(tiny_checkpoint, tmp_path, monkeypatch):
    import builtins

    from difareli.cli.relight import run
    from skimage import data

    photo = tmp_path / "astronaut.png"
    iio.imwrite(photo, data.astronaut())
    real_import = builtins.__import__

    def no_mediapipe(name, *args, **kwargs):
        if name.split(".")[0] == "mediapipe":
            raise ImportError("No module named 'mediapipe'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_mediapipe)
    cfg = compose_train(tmp_path, [f"checkpoint={tiny_checkpoint('difareli_pp')}", f"image={photo}",
                                   "target.yaw=45", "progress=false", "runtime.device=cpu"], config_name="relight")
    with pytest.raises(ImportError, match="DIFARELI_PREPROCESS=1 bash scripts/install.sh"):
        run(cfg)


def test_relight_needs_exactly_one_source(tiny_checkpoint, synth_store, tmp_path):
    from difareli.cli.relight import run

    ckpt = tiny_checkpoint("difareli_pp")
    for extra in ([], [f"store={synth_store}", f"image={tmp_path / 'x.jpg'}"]):
        cfg = compose_train(tmp_path, [f"checkpoint={ckpt}", "target.yaw=45", *extra], config_name="relight")
        with pytest.raises(ValueError, match="either store="):
            run(cfg)


@pytest.mark.skipif(not HAS_ESTIMATORS, reason="photo estimators not installed (DIFARELI_PREPROCESS=1)")
@pytest.mark.skipif(not zoo.available(), reason="no shipped checkpoint")
def test_relight_a_photo_in_one_command(tmp_path):
    from difareli.cli.relight import run
    from skimage import data

    photo = tmp_path / "astronaut.jpg"
    iio.imwrite(photo, data.astronaut())
    name = "difareli_pp-synth64" if "difareli_pp-synth64" in zoo.available() else zoo.available()[0]
    cfg = compose_train(tmp_path, [f"checkpoint={name}", f"image={photo}", "target.yaw=45", "sampler=unipc",
                                   "sampler.steps=10", "progress=false", "runtime.device=cpu"],
                        config_name="relight")
    written = run(cfg)
    relit = iio.imread(written["image"])
    comparison = iio.imread(written["comparison"])
    # With its header, the 64 px crops shown 4x (a face at least 256 px tall).
    assert relit.shape == (64, 64, 3) and comparison.shape[1:] == (2 * 258 + 2, 3) and comparison.shape[0] > 258
    src = comparison[-258:-2, 2:258][::4, ::4].astype(float)
    assert src.std() > 10  # the aligned face crop, not a blank
    assert np.abs(relit.astype(float) - src).mean() > 1.0  # the light changed the image


def test_the_demos_suite_verdict_is_one_line_with_the_suites_paired_test():
    from difareli.cli.demo import suite_verdict

    suite = zoo.suite()
    if suite is None:
        pytest.skip("no shipped suite")
    line = suite_verdict(suite, "difareli_pp_ss_est-synth64")  # the demo's default, in the pooled fresh seeds
    assert "\n" not in line and line.startswith("the shipped suite (300 pairs per protocol of unseen seeds")
    assert "same subject 0.147, better than the Lambertian ratio image's 0.183 (p = 4.2e-42)" in line
    assert "different subject 0.188, better than the Lambertian ratio image's 0.291 (p = 1.7e-48)" in line
    assert suite_verdict(suite, "not-shipped") is None


def test_the_demo_makes_its_own_lights_plausible(synth_store):
    from types import SimpleNamespace

    from difareli.data.store import EncodingStore
    from difareli.relight.request import plausible  # the demo's lights and its rotation (Rotation(plausible=True))
    from difareli.lighting import sh
    from difareli.relight.targets import Targets

    store = EncodingStore.open(synth_store)
    arrays = store.read(store.ids()[0], ["light", "normal"])
    arrays["light"] = arrays["light"].astype(np.float64)
    arrays["light"][0] *= 0.3  # a strongly directional light, as photos give: its back turn is negative
    turned = sh.rotate(arrays["light"], sh.rotation_frames("yaw", 8)[1])
    n = arrays["normal"][np.linalg.norm(arrays["normal"], axis=-1) > 0.5]
    assert min(sh.irradiance(light, n).min() for light in turned) < 0
    out = plausible(Targets.of(turned, [None] * 8), SimpleNamespace(arrays=arrays))
    assert all(sh.irradiance(light, n).min() >= 0 for light in out.lights)
    np.testing.assert_allclose([sh.irradiance(light, n).mean() for light in out.lights],
                               sh.irradiance(arrays["light"], n).mean(), rtol=1e-6)


def test_the_demo_labels_its_live_table_and_prints_the_cards():
    """The demo's few pairs cannot rank methods: it says so and prints the card's measured table."""
    from difareli.cli.demo import card_benchmark

    card = card_benchmark("difareli_pp-synth64")
    assert card is not None and "100 test pairs per protocol" in card and "| identity |" in card


def test_the_demos_verdict_reads_the_suites_first_table_only():
    """A suite with a pooled table first and per-store tables after: the verdict is the pooled table's row and
    its own paired test, never a later table's row of the same label."""
    from difareli.cli.demo import suite_verdict

    head = "| Method | (i) same subject DSSIM | (ii) different subject DSSIM |\n|---|---:|---:|\n"
    paired = ("| protocol | metric | A | B | n | mean(B - A) | 95% CI | Wilcoxon p |\n"
              "|---|---|---|---|---:|---:|---|---:|\n"
              "| (i) same subject | DSSIM | lambertian | m/unipc-50 | 300 | -0.01 | [-0.02, -0.005] | 0.001 |\n"
              "| (ii) different subject | DSSIM | lambertian | m/unipc-50 | 300 | -0.06 | [-0.07, -0.05] | 2e-30 |\n")
    pooled = ("**Pooled: a, b, c** (300 different, 300 same pairs in all). "
              "Rows: `m/unipc-50` = `m-synth64` (unipc-50).\n\n"
              + head + "| identity | 0.2600 ± 0.01 | 0.2600 ± 0.01 |\n| lambertian | 0.1830 ± 0.01 | 0.2910 ± 0.01 |\n"
              "| m/unipc-50 | 0.1750 ± 0.01 | 0.2300 ± 0.01 |\n\n" + paired)
    later = ("**a**: 100 pairs per protocol. Rows: `m/unipc-50` = `m-synth64` (unipc-50).\n\n" + head
             + "| identity | 0.9 ± 0.01 | 0.9 ± 0.01 |\n| lambertian | 0.1 ± 0.01 | 0.1 ± 0.01 |\n"
             "| m/unipc-50 | 0.5 ± 0.01 | 0.5 ± 0.01 |\n")
    line = suite_verdict(pooled + "\n" + later, "m-synth64")
    assert line == ("the shipped suite (300 pairs per protocol of unseen seeds, DSSIM, lower is better): "
                    "same subject 0.175, better than the Lambertian ratio image's 0.183 (p = 0.001), the unrelit "
                    "input 0.260; different subject 0.230, better than the Lambertian ratio image's 0.291 "
                    "(p = 2e-30), the unrelit input 0.260")
    assert suite_verdict(later + "\n" + pooled, "m-synth64").startswith(
        "the shipped suite (100 pairs per protocol of unseen seeds, DSSIM, lower is better): same subject 0.500, "
        "level with")  # a per-store table first: its own rows, and no paired line there: level with
    assert suite_verdict(pooled, "other-synth64") is None
