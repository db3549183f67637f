"""Cases that used to end silently or with a traceback: each is now a one-line error (or a warning)
naming the input and the fix, and nothing is written half."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from difareli.errors import NonFiniteError, UserError
from difareli.lit import LoadedCheckpoint
from difareli.relight.relighter import Relighter
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets

from tests.helpers import compose_train


def test_fast_dev_run_keeps_the_ema_callback_an_optuna_sweep_tunes(tmp_path):
    cfg = compose_train(tmp_path, ["debug=fdr", "hparams_search=optuna", "callbacks.ema.decay=0.999"])
    assert cfg.callbacks.ema.decay == 0.999 and cfg.trainer.fast_dev_run
    assert "model_checkpoint" not in cfg.callbacks  # still no checkpoint litter in debug runs


def test_trainer_gpu_without_a_gpu_is_one_line(tmp_path, monkeypatch):
    from difareli.cli.train import train

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = compose_train(tmp_path, ["trainer=gpu", "debug=fdr"])
    with pytest.raises(UserError,
                       match=r"trainer.accelerator=gpu but this machine has no usable CUDA GPU.*trainer=cpu"):
        train(cfg)


def test_resuming_into_another_variant_names_both(tiny_checkpoint, synth_store, tmp_path):
    from difareli.cli.train import train

    cfg = compose_train(tmp_path, [f"data.root={synth_store}", "data.resolution=32", "data.synth=null",
                                   "model=difareli", "model.preset=tiny", "trainer=cpu", "trainer.max_steps=1",
                                   "sample_grid=false", "logger=[]", f"ckpt_path={tiny_checkpoint('difareli_pp')}"])
    with pytest.raises(UserError, match=r"trained as model variant 'difareli_pp', this run composes 'difareli'"):
        train(cfg)


def test_checkpoint_naming_an_unknown_module_class(tiny_checkpoint, tmp_path):
    from difareli.lit import load_checkpoint

    ckpt = torch.load(tiny_checkpoint("difareli_pp"), map_location="cpu", weights_only=True)
    ckpt["difareli_module"] = "difareli.lit.future.FutureModule"
    torch.save(ckpt, tmp_path / "future.ckpt")
    with pytest.raises(ValueError, match=r"this difareli version does not have .*written by another version"):
        load_checkpoint(tmp_path / "future.ckpt")


@pytest.fixture()
def store_copy(synth_store, tmp_path):
    root = tmp_path / "store"
    shutil.copytree(synth_store, root)
    return root


def test_empty_or_malformed_meta_is_named_not_dropped_from_the_split(store_copy):
    from difareli.cli.store import verify

    rid = EncodingStore.open(store_copy).ids(split="test")[0]
    (store_copy / "records" / rid / "meta.json").write_text("{}")
    with pytest.raises(UserError, match=r"1 record\(s\) .* have no 'split'"):
        EncodingStore.open(store_copy).ids(split="test")
    assert any(p.startswith(f"{rid}: meta.json lacks ['split', 'subject', 'light_index']") for p in verify(store_copy))
    (store_copy / "records" / rid / "meta.json").write_text("{not json")
    with pytest.raises(UserError, match=r"meta.json is not JSON"):
        EncodingStore.open(store_copy).meta(rid)
    assert any("meta.json unreadable" in p for p in verify(store_copy))


def test_verify_checks_lights_like_the_readers(store_copy):
    from difareli.cli.store import verify

    rid = EncodingStore.open(store_copy).ids()[0]
    light = np.load(store_copy / "records" / rid / "light.npy")
    np.save(store_copy / "records" / rid / "light.npy", (light * 0 + 5e4).astype(np.float32))
    assert any(p.startswith(f"{rid}: light unreadable") and "exceeds" in p for p in verify(store_copy))


def test_a_target_light_far_brighter_than_any_face_is_refused():
    light = np.zeros((9, 3))
    light[0] = 9.9e3  # under the stored-light bound, but it only relights to saturated noise
    with pytest.raises(NonFiniteError, match=r"magnitude 9.9e\+03 exceeds 100"):
        Targets.of([light])
    Targets.of([light / 1e3])  # a bright but plausible light


def test_rotation_with_a_million_frames_is_refused_before_any_work(tmp_path):
    from difareli.relight.request import Request

    cfg = compose_train(tmp_path, ["checkpoint=difareli_pp-synth64", "image=x.png", "video.axis=yaw",
                                   "video.frames=1000000"], config_name="relight")
    with pytest.raises(UserError, match=r"video.frames=1000000 is invalid: must be an integer from 1 to 3600"):
        Request.from_config(cfg)


class Saturating(torch.nn.Module):
    """A one-pass model that relights every image to white: what an unstable sampler's noise looks like."""

    spatial_inputs, nonspatial_inputs = ["shading"], []

    def condition(self, spatial, nonspatial):
        return spatial

    def relight_once(self, x0, source, target):
        return torch.ones_like(x0)


def test_saturated_relights_are_reported(synth_store):
    r = Relighter(LoadedCheckpoint(Saturating(), {}, {}, 0), None, device="cpu")
    source = r.source(EncodingStore.open(synth_store), "s00006_l0")
    with pytest.warns(RuntimeWarning, match=r"over 50% of their values clipped .* try more steps"):
        out = r.relight(source, Targets.of([source.arrays["light"]]))
    assert (out == 255).all()


@pytest.mark.slow
def test_a_multirun_with_one_bad_job_runs_the_others_and_ends_with_a_summary(synth_store, tmp_path):
    import os
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "difareli.cli.train", "-m", "debug=fdr", f"data.root={synth_store}",
           "data.resolution=32", "data.synth=null", "model.preset=tiny,nope", f"paths.log_dir={tmp_path}",
           "sample_grid=false"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "2 job(s): 1 completed, 1 failed" in proc.stderr
    assert "job 1 (" in proc.stderr and "model.preset=nope" in proc.stderr and "unknown UNet preset" in proc.stderr
    summary = next(tmp_path.rglob("sweep_summary.json"))
    assert json.loads(summary.read_text())["completed"] == 1
