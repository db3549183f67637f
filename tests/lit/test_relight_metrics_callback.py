"""The relight-metrics callback: its validation pairs, what a training run logs, and parity of its numbers with
difareli-benchmark's scoring of the same relights (diffusion model and one-pass student)."""

import csv
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from difareli.lit.relight_metrics import RelightMetrics, validation_pairs
from difareli.data.store import EncodingStore

from tests.helpers import compose_train

pytestmark = pytest.mark.usefixtures("one_thread")


def test_validation_pairs_follow_the_protocols(synth_store):
    store = EncodingStore.open(synth_store)
    pairs = validation_pairs(store, "val", 3)
    assert 0 < len(pairs) <= 3
    val = set(store.ids(split="val"))
    for p in pairs:
        src, tgt, other = (store.meta(p[k]) for k in ("source", "target", "different"))
        assert {p["source"], p["target"], p["different"]} <= val and p["same"] == p["target"]
        assert src["subject"] == tgt["subject"] != other["subject"] and src["light_index"] != tgt["light_index"]
        assert other["light_index"] == tgt["light_index"] and other["light_group"] == tgt["light_group"]
    assert validation_pairs(store, "val", 3) == pairs  # fixed
    assert validation_pairs(store, "nope", 3) == []


def test_due_every_n_steps():
    cb = RelightMetrics(every_n_steps=300)
    tr = SimpleNamespace(sanity_checking=False, global_step=100)
    assert not cb._due(tr)  # nothing prepared (no fit: e.g. trainer.validate)
    cb.cases = [{}]
    assert cb._due(tr)
    cb._last_step = 100
    for step, due in ((300, False), (400, True)):
        tr.global_step = step
        assert cb._due(tr) is due
    assert not cb._due(SimpleNamespace(sanity_checking=True, global_step=900))
    with pytest.raises(ValueError, match="unknown sampler preset"):
        RelightMetrics(sampler="nope")
    with pytest.raises(ValueError, match="every_n_steps=0 must be null or an int >= 1"):
        RelightMetrics(every_n_steps=0)
    with pytest.raises(ValueError, match="target_sun='sun': use one of shadows, peak"):
        RelightMetrics(target_sun="sun")
    with pytest.raises(ValueError, match="precision='fp16': use one of auto, fp32, bf16"):
        RelightMetrics(precision="fp16")


def test_targets_are_the_benchmarks_and_a_non_finite_relight_skips_the_evaluation(synth_store, tiny_checkpoint):
    from difareli.checkpoints.loading import load_checkpoint
    from difareli.evaluation.pairs import Lights, Pair
    from difareli.lighting.light_fit import LightFit

    store = EncodingStore.open(synth_store)
    model = load_checkpoint(tiny_checkpoint("difareli_pp")).model.eval()
    pairs = validation_pairs(store, "val", 2)
    marched = RelightMetrics(extras=False, precision="fp32")
    marched.prepare(store, model, pairs)
    peak = RelightMetrics(extras=False, precision="fp32", target_sun="peak")
    peak.prepare(store, model, pairs)
    lights = Lights(store, LightFit(), sun_from_shadows=True)
    for case, p in zip(marched.cases, pairs):
        want = [Pair(long, p["source"], p[short], p["target"]) for long, short in
                (("same_subject", "same"), ("different_subject", "different"))]
        t = case["targets"]
        assert np.allclose(t.lights, [lights.for_pair(w)[0] for w in want])
        assert t.shadows == tuple(lights.for_pair(w)[1] for w in want)
        assert all(np.allclose(a, b) for a, b in zip(t.suns, [lights.sun(w) for w in want]))
    assert all(s is None for c in peak.cases for s in c["targets"].suns)
    assert any(s is not None for c in marched.cases for s in c["targets"].suns)  # a shadowed record has a key sun
    trainer = SimpleNamespace(global_step=7, is_global_zero=True, default_root_dir="unused", loggers=[])
    other = load_checkpoint(tiny_checkpoint("difareli_pp")).model.eval()
    with pytest.raises(ValueError, match="the module it was prepared with"):
        marched.evaluate(trainer, other)
    # A diverging model: the evaluation is skipped with a warning, nothing is logged, training mode comes back.
    with torch.no_grad():
        next(model.parameters()).fill_(float("nan"))
    model.train()
    with pytest.warns(RuntimeWarning, match="relight metrics at step 7 skipped: relight of .*NaN or Inf"):
        assert marched.evaluate(trainer, model) == {}
    assert model.training and marched.history == [] and marched._last_step == 7
    # Under DDP the processes decide together: one process's NaN makes every process skip (none waits alone).
    decided = []
    ddp = SimpleNamespace(**vars(trainer), world_size=2, strategy=SimpleNamespace(
        reduce_boolean_decision=lambda d, all=True: decided.append((d, all)) or True))
    with torch.no_grad():
        next(peak.relighter.model.parameters()).copy_(next(other.parameters()))  # finite again here
    with pytest.warns(RuntimeWarning, match="another process is not finite"):
        assert peak.evaluate(ddp, peak.relighter.model) == {}
    assert decided == [(False, False)]  # this process's relights were finite: "any" of the processes decided


def test_every_process_gets_a_pair_or_none_does(synth_store):
    store = EncodingStore.open(synth_store)
    have = len(validation_pairs(store, "val", 100))
    datamodule = SimpleNamespace(store=store, val_split="val")

    def start(world):
        cb = RelightMetrics(pairs=1, extras=False)
        cb.prepare = lambda store, module, pairs, step: setattr(cb, "cases", list(pairs))
        tr = SimpleNamespace(fast_dev_run=False, datamodule=datamodule, global_rank=world - 1, world_size=world,
                             global_step=0)
        cb.on_fit_start(tr, _relightable())
        return cb

    assert len(start(2).cases) == 1  # pairs=1, 2 processes: 2 pairs asked for, the last process's share is one
    with pytest.warns(UserWarning, match=f"gives {have} validation pair\\(s\\) for {have + 1} processes"):
        cb = start(have + 1)
    assert not cb.enabled and cb.cases == []


def _relightable():
    from difareli.relight.relightable import Relightable

    class Module(Relightable):
        spatial_inputs, nonspatial_inputs = ["shading"], ["cam"]

    return Module()


def _train(out: Path, synth_store, *extra):
    from difareli.cli.train import train

    cfg = compose_train(out, [
        f"data.root={synth_store}", "data.resolution=32", "data.synth=null", "data.num_workers=0", "data.batch_size=4",
        "model.preset=tiny", "trainer=cpu", "trainer.max_steps=4", "trainer.val_check_interval=2",
        "trainer.limit_val_batches=1", "sample_grid=false", "logger=csv", "callbacks.ema.decay=0.9",
        "callbacks.relight_metrics.pairs=2", "callbacks.relight_metrics.steps=3", *extra])
    return train(cfg)


def _logged(out: Path) -> list[dict]:
    path = next(out.rglob("metrics.csv"))
    return [r for r in csv.DictReader(path.open()) if r.get("val/dssim/same")]


def _independent(ckpt, store, pairs, sampler):
    """What difareli-benchmark computes for the same pairs, written out here: its diffusion Method relights (uint8,
    one target per call), the light fitted to the light-source image, its target c, the key sun found from that
    image's cast shadows (the model reads shadow maps), benchmark.score."""
    from difareli.evaluation.baselines import DiffusionMethod
    from difareli.evaluation.benchmark import score
    from difareli.evaluation.pairs import StoredFace
    from difareli.lighting.light_fit import LightFit
    from difareli.data.target_shadow import target_shadow_of
    from difareli.render.sun_fit import record_sun

    method = DiffusionMethod(str(ckpt), sampler, runtime={"device": "cpu", "precision": "fp32"})
    marches = "shadow_map" in method.relighter.model_inputs
    fit, out, suns = LightFit(), {"same": [], "different": []}, 0
    for p in pairs:
        gt = store.read(p["target"], ["image", "face_mask"])
        for k in ("same", "different"):
            light = fit.from_store(store, p[k])
            found = record_sun(store, p[k], light, fit=fit) if marches else None
            suns += found is not None
            relit = method.relight(StoredFace(store, p["source"]), light, target_shadow_of(store, p[k])[0],
                                   target_sun=None if found is None else found.direction)
            out[k].append(score(relit, gt["image"], gt["face_mask"]))
    assert suns == (2 * len(pairs) if marches else 0)
    return {f"val/{m}/{k}": float(np.mean([s[m] for s in v])) for k, v in out.items()
            for m in ("dssim", "mse", "lpips")}


def _check_parity(run, synth_store, ckpt, sampler):
    from difareli.lit import load_checkpoint

    cb = next(c for c in run["trainer"].callbacks if isinstance(c, RelightMetrics))
    assert [h["step"] for h in cb.history] == [2, 4] and cb.history[-1]["seconds"] > 0
    store = EncodingStore.open(synth_store)
    pairs = [c["pair"] for c in cb.cases]
    # The final weights (the EMA average copied in at train end), scored by the callback and independently.
    model = load_checkpoint(ckpt).model.eval()
    # Both sides in fp32: the same computation to float rounding (bf16 rounds batch 2 and batch 1 differently).
    fresh = RelightMetrics(pairs=2, sampler=sampler["name"], steps=sampler.get("steps"), precision="fp32")
    fresh.prepare(store, model, pairs)  # what on_fit_start does (extras=true, the default)
    assert {"val/light_angle/same", "val/light_rel_error/different"} <= set(cb.history[-1])  # logged in training
    trainer = SimpleNamespace(global_step=99, is_global_zero=True, default_root_dir=str(ckpt.parent), loggers=[],
                              sanity_checking=False)
    with pytest.warns(UserWarning, match="self.log"):
        ours = fresh.evaluate(trainer, model)
    ref = _independent(ckpt, store, pairs, sampler)
    base = {k: v for k, v in ours.items() if k.split("/")[1] in ("dssim", "mse", "lpips")}
    assert set(base) == set(ref) and len(base) == 6
    # the extra metrics of the same relights (difareli.evaluation.extras): what the benchmark writes beside them
    extra = {k.split("/")[1] for k in ours} - {"dssim", "mse", "lpips"}
    assert {"light_angle", "light_rel_error"} <= extra and all(0 <= ours[f"val/light_angle/{p}"] <= 180
                                                               for p in ("same", "different"))
    for k in base:
        # decoded in one batch of 2 here, one target per call there: float32 rounding may move a pixel a level
        assert ours[k] == pytest.approx(ref[k], rel=1e-4, abs=1e-7), k
    return cb


@pytest.mark.slow  # a training run with relight metrics and a benchmark: the default run has to finish in minutes at
# load 4
def test_training_logs_relight_metrics_and_grid_and_they_match_the_benchmark(synth_store, tmp_path, capsys):
    run = _train(tmp_path, synth_store)
    rows = _logged(tmp_path)
    assert [int(r["step"]) for r in rows] == [1, 3]  # Lightning logs a validation at the last step's index
    for r in rows:
        for k in ("dssim", "mse", "lpips"):
            for p in ("same", "different"):
                assert 0 < float(r[f"val/{k}/{p}"]) < 1
    assert sorted(p.name for p in (tmp_path / "grids").glob("relight_metrics_step*.png")) == [
        "relight_metrics_step0000002.png", "relight_metrics_step0000004.png"]
    out = capsys.readouterr().out
    assert "relight metrics at step 2: 4 relights (unipc-3, rule paper) in " in out and "% of the " in out
    _check_parity(run, synth_store, tmp_path / "checkpoints" / "last.ckpt", {"name": "unipc", "steps": 3})


def test_student_runs_one_pass(synth_store, tmp_path, capsys):
    run = _train(tmp_path, synth_store, "model=student", "data.pairs=gt")
    assert _logged(tmp_path)
    assert "4 relights (one pass, rule paper)" in capsys.readouterr().out
    _check_parity(run, synth_store, tmp_path / "checkpoints" / "last.ckpt", {"name": "unipc", "steps": 3})
