"""An imported official checkpoint (or any checkpoint) used on a store whose encodings it cannot read: one line
naming the checkpoint, what it expects, what the store gives and the fix, before any relight or training step
(it failed on a tensor-size mismatch inside the model's normalisation)."""

from __future__ import annotations

import pytest

from difareli.checkpoints.loading import read_checkpoint
from difareli.data.inputs import check_store_fits
from difareli.data.store import EncodingStore
from difareli.errors import UserError
from difareli.evaluation.baselines import DiffusionMethod
from difareli.evaluation.benchmark import run_benchmark
from difareli.official import weights as official

from tests.helpers import HAS_DLIB_MODELS, HAS_ESTIMATORS, compose_train
from tests.official.test_official_checkpoint import write_run


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """A tiny official checkpoint (16 px; condition shape 156 + cam 3 + faceemb 512 + shadow 1) imported."""
    tmp = tmp_path_factory.mktemp("official")
    run, cfg, _ = write_run(tmp)
    official.import_checkpoint(run, cfg, tmp / "o.ckpt")
    return tmp / "o.ckpt"


def expected(ckpt, store) -> str:
    return (f"checkpoint={ckpt} cannot read store {store}: it expects 16 px, spatial inputs shading, background "
            "(6 channels) and a non-spatial condition of 672 values (shape, cam, identity, shadow); the store "
            "(synthfaces, 32 px) gives 6 channels (shading 3, background 3) and 185 values (shape 53, cam 3, "
            f"identity 128, shadow 1); use a checkpoint trained on a store like this one (difareli-train "
            f"data.root={store}), or a store made like the checkpoint's training data (an imported official "
            "checkpoint reads stores written by difareli.official.importers)")


def test_imported_checkpoint_on_a_synthfaces_store_names_both(imported, synth_store):
    config = read_checkpoint(imported)["hyper_parameters"]
    with pytest.raises(UserError) as e:
        check_store_fits(config, EncodingStore.open(synth_store), imported)
    assert str(e.value) == expected(imported, synth_store)


def test_a_checkpoint_that_fits_passes_and_a_resolution_alone_is_not_refused(synth_store):
    store = EncodingStore.open(synth_store)
    config = {"spatial_inputs": ["shading", "shadow_map", "masks"], "nonspatial_inputs": ["shape", "cam", "identity"],
              "input_dims": {"spatial_channels": 18, "nonspatial_dim": 184, "resolution": 64}}
    check_store_fits(config, store, "difareli_pp-synth64")  # the shipped model's sizes; trained at 64 px
    check_store_fits({"name": "a pipeline"}, store)  # nothing recorded: nothing to check
    config["input_dims"]["spatial_channels"] = 17
    with pytest.raises(UserError, match=r"expects 64 px, spatial inputs shading, shadow_map, masks \(17 channels\) "
                                        r".* gives 18 channels \(shading 3, shadow_map 1, masks 14\) and 184 values"):
        check_store_fits(config, store, "x.ckpt")
    config["spatial_inputs"] = ["shading", "albedo"]
    with pytest.raises(UserError, match=r"the store \(synthfaces, 32 px\) lacks \['albedo'\]; "):
        check_store_fits(config, store, "x.ckpt")


def test_benchmark_refuses_before_any_pair(imported, synth_store, tmp_path):
    method = DiffusionMethod(str(imported), {"name": "ddim", "steps": 2})
    store = EncodingStore.open(synth_store)
    with pytest.raises(UserError) as e:  # it had ended in a tensor-size mismatch (RuntimeError)
        run_benchmark(store, method, ["same_subject"], tmp_path / "bench", limit=2, progress=False, grid_pairs=0)
    assert str(e.value) == expected(imported, synth_store)
    assert not (tmp_path / "bench").exists()


def test_training_from_it_on_the_store_is_refused_before_the_model_is_built(imported, synth_store, tmp_path):
    from difareli.cli.train import train

    cfg = compose_train(tmp_path / "run", [f"data.root={synth_store}", "data.resolution=32", "data.synth=null",
                                           "data.num_workers=0", "model=difareli", "model.preset=tiny",
                                           "trainer=cpu", "trainer.max_steps=1", "logger=[]", "sample_grid=false",
                                           f"init_from={imported}"])
    with pytest.raises(UserError) as e:  # it had stopped on "nonspatial_stats needs 185 means ... got 672"
        train(cfg)
    assert str(e.value) == expected(imported, synth_store)


needs_estimators = pytest.mark.skipif(not (HAS_ESTIMATORS and HAS_DLIB_MODELS),
                                      reason="photo estimators not installed (DIFARELI_PREPROCESS=1)")


@needs_estimators
def test_imported_16px_checkpoint_on_a_photo_names_the_model_not_the_skin(imported, monkeypatch):
    from skimage import data as skdata

    from difareli.relight import photo
    from difareli.relight.relighter import Relighter

    ran = []
    monkeypatch.setattr(photo, "prepare_photo", lambda *a, **k: ran.append(a))  # never run: the model said first
    relighter = Relighter(str(imported))
    with pytest.raises(UserError) as e:  # it had said "too few usable skin pixels for the light fit (6 < 100)"
        relighter.photo_source(skdata.astronaut())
    assert str(e.value) == (
        f"checkpoint={imported} cannot relight photo: it expects 16 px, spatial inputs shading, background (6 "
        "channels) and a non-spatial condition of 672 values (shape, cam, identity, shadow); what the photo estimators "
        "write (difareli-preprocess's) gives 6 channels (shading 3, background 3) and 185 values (shape 53, cam 3, "
        "identity 128, shadow 1); relight photos with a checkpoint trained on such encodings (e.g. "
        "difareli_pp-synth64), or this one on a store made like its training data (an imported official "
        "checkpoint reads stores written by difareli.official.importers)")
    assert ran == []


@needs_estimators
def test_a_crop_too_small_for_the_estimators_names_its_size(monkeypatch):
    from skimage import data as skdata

    from difareli.relight import photo
    from difareli.relight.relighter import Relighter

    ran = []
    monkeypatch.setattr(photo, "prepare_photo", lambda *a, **k: ran.append(a))
    relighter = Relighter("difareli_pp_ss-synth64")  # reads the estimators' encodings: only the size is wrong
    with pytest.raises(UserError, match=r"^photo_size=16 is too small for the photo estimators \(a face crop under "
                                        r"32 px holds too few skin pixels to fit its light\); give photo_size=32 "
                                        "or more$"):
        relighter.photo_source(skdata.astronaut(), size=16)
    relighter.resolution = 24  # a model trained at 24 px, the crop size by default
    with pytest.raises(UserError, match=r"^checkpoint=difareli_pp_ss-synth64 was trained at 24 px, too small a face "
                                        r"crop .* give photo_size=32 or more \(the model then runs outside its 24 "
                                        r"px\), or a checkpoint trained at 32 px or more$"):
        relighter.photo_source(skdata.astronaut())
    assert ran == []
    photo.check_photo_size(photo.MIN_PHOTO_SIZE, "x", given=True)  # the smallest crop the light fit was seen to fit
