"""Shipped checkpoints by name (difareli.checkpoints.zoo): slim export round trip, model cards, name resolution, and the
shipped references themselves (loadable with weights_only=True, they change the light of an unseen face)."""

from __future__ import annotations

import runpy
from pathlib import Path

import numpy as np
import pytest
import torch

from difareli.lighting import sh
from difareli.checkpoints import loading, zoo
from difareli.lit import load_checkpoint
from difareli.checkpoints.loading import read_checkpoint
from difareli.relight.relighter import Relighter
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets

pytestmark = pytest.mark.usefixtures("one_thread")
FACTS = {"summary": "a test export", "data": "SynthFaces 32 px", "seed": 42, "licence": "BFM: non-commercial",
         "benchmark": "| method | DSSIM |\n|---|---|\n| x | 0.1 |", "intended_use": "tests"}


def test_export_is_slim_and_relights_bit_for_bit(tiny_checkpoint, synth_store, tmp_path):
    run = tiny_checkpoint("difareli_pp")
    path, card = zoo.export(run, "test_pp", FACTS, out_dir=tmp_path)
    raw = torch.load(path, map_location="cpu", weights_only=True)
    assert "optimizer_states" not in raw and "callbacks" not in raw
    assert path.stat().st_size < 0.6 * run.stat().st_size  # no AdamW moments
    assert raw["model_card"]["seed"] == 42
    text = card.read_text()
    for piece in ("# test_pp", "| seed | 42 |", "BFM: non-commercial", "| x | 0.1 |", "| steps | 20 |"):
        assert piece in text
    # A fine-tune's card states the steps of the checkpoint it started from (release_reference's "steps" fact).
    ft, card2 = zoo.export(run, "test_ft", {**FACTS, "steps": "520 in all: 500 of test_pp, then 20"}, out_dir=tmp_path)
    assert "| steps | 520 in all: 500 of test_pp, then 20 |" in card2.read_text()
    # A fine-tune of that fine-tune starts from all 520 steps, not from the 20 of its last run.
    release = runpy.run_path(str(Path(__file__).parents[2] / "scripts" / "release_reference.py"))
    assert release["total_steps"](read_checkpoint(str(ft))) == 520
    assert release["total_steps"](read_checkpoint(str(path))) == read_checkpoint(str(path))["global_step"] > 0
    assert release["fine_tuned_data"](read_checkpoint(str(ft))) == "SynthFaces 32 px"  # same data as it started from
    assert release["fine_tuned_data"](None) is None
    store = EncodingStore.open(synth_store)
    rid = store.ids(split="test")[0]
    light = sh.yaw(np.asarray(store.read(rid, ["light"])["light"]), 45.0)
    spec = {"name": "ddim", "steps": 4}
    a = _relight_once(Relighter(run, spec, device="cpu"), store, rid, light)
    b = _relight_once(Relighter(str(path), spec, device="cpu"), store, rid, light)
    np.testing.assert_array_equal(a, b)
    # bf16 weights (what a lent GPU sends back): half the size, relit images within a few levels
    half, _ = zoo.export(run, "test_pp_bf16", FACTS, out_dir=tmp_path, dtype=torch.bfloat16)
    assert half.stat().st_size < 0.6 * path.stat().st_size
    c = _relight_once(Relighter(str(half), spec, device="cpu"), store, rid, light)
    assert np.abs(c.astype(int) - a.astype(int)).mean() < 4


def test_names_resolve_and_errors_list_them(tiny_checkpoint, tmp_path, monkeypatch):
    monkeypatch.setattr(zoo, "SHIPPED_DIR", tmp_path)
    zoo.export(tiny_checkpoint("difareli"), "mini-synth32", FACTS, out_dir=tmp_path)
    assert zoo.available() == ["mini-synth32"]
    assert loading.resolve("mini-synth32") == tmp_path / "mini-synth32.ckpt"
    loaded = load_checkpoint("mini-synth32")
    assert loaded.config["name"] == "difareli" and loaded.global_step == 20
    with pytest.raises(FileNotFoundError, match="mini-synth32"):
        loading.resolve("no-such-model")
    assert "mini-synth32" in zoo.card("mini-synth32")


# A diffusion model at its default sampler (UniPC-50) on 12 relights is about a minute: the slow tier; the
# one-pass student stays in the default run.
SHIPPED = [pytest.param(n, marks=pytest.mark.slow) if "DiffusionModule" in zoo.card(n) else n for n in zoo.available()]


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_checkpoint_changes_the_light_of_an_unseen_face(name, tmp_path):
    card = zoo.card(name)
    for piece in ("| steps |", "| hardware |", "| precision |", "## Benchmark", "Basel Face Model"):
        assert piece in card, piece
    loaded = load_checkpoint(name)
    res = loaded.config["input_dims"]["resolution"]
    from difareli.synth.generator import generate

    generate(out_dir=str(tmp_path / "s"), subjects=10, lights=2, resolution=res, seed=77, realism="full",
             inputs="estimated_light")
    store = EncodingStore.open(tmp_path / "s")
    r = Relighter(loaded, device="cpu")  # the default sampler (the cards'), or one pass for a student
    own_errors = []
    for rid in store.ids(split="test"):  # the unseen faces of the test split (4 records here)
        arrays = store.read(rid, ["image", "light", "shadow"])
        own = np.asarray(arrays["light"])
        c = float(np.asarray(arrays["shadow"]).reshape(-1)[0])
        same, left, right = r.relight(r.source(store, rid),
                                      Targets.of([own, sh.yaw(own, -60.0), sh.yaw(own, 60.0)], [c] * 3))
        image = np.asarray(arrays["image"]).astype(float)
        own_errors.append(np.abs(same - image).mean())
        # Lights from either side change the image visibly and differently (17-41 levels apart).
        assert np.abs(left.astype(float) - right).mean() > 3 * own_errors[-1], rid
    # Its own light gives the input back closely on average over the unseen faces (on these seed-77 faces, at the
    # default bf16 on an AMX CPU: difareli_pp-synth64 3.2-4.1 grey levels, mean 3.7 (8,212 steps);
    # difareli_pp_ss-synth64 3.7-7.5, mean 5.2 (LPIPS fine-tuned); difareli-synth64 2.1-2.9, mean 2.5; at bf16 on an
    # AVX-512 EPYC difareli_pp_ss_v3-synth64 2.4-6.3, mean 4.1, against 3.6-6.5, mean 5.1 for difareli_pp_ss-synth64).
    assert np.mean(own_errors) < 8, own_errors


def _relight_once(relighter, store, rid, light):
    return relighter.relight(relighter.source(store, rid), Targets.of([light], [0.0]))


def test_one_recommended_model_is_every_default():
    """The app, the demo and the photo benches default to one shipped model (zoo.RECOMMENDED), which is shipped."""
    from omegaconf import OmegaConf

    from difareli.evaluation import photo_path

    conf = Path(__file__).resolve().parents[2] / "conf"
    assert zoo.RECOMMENDED in zoo.available()
    assert OmegaConf.load(conf / "app.yaml").checkpoint == zoo.RECOMMENDED
    assert OmegaConf.load(conf / "demo.yaml").checkpoint == zoo.RECOMMENDED
    assert photo_path.DEFAULT_CHECKPOINT == zoo.RECOMMENDED
