"""difareli-bench-samplers and difareli.perf.samplers: what is timed, the error columns, and the written table/plots."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from torch import nn

from difareli.perf import samplers as speed
from difareli.cli.bench_samplers import run
from difareli.diffusion import PRESETS
from difareli.diffusion.schedule import DiffusionSchedule
from difareli.data.store import EncodingStore

from tests.helpers import compose_train

pytestmark = pytest.mark.usefixtures("one_thread")
DDIM = PRESETS["ddim"].to_config()  # a sampler config as conf/sampler/ddim.yaml holds it


def compose(out: Path, overrides: list[str]):
    return compose_train(out, [*overrides, "progress=false", "runtime.device=cpu"], config_name="bench_samplers")


def read_csv(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


class SleepyModel(nn.Module):
    """Every network pass sleeps a known time: the Modulator 20 ms, the denoiser 5 ms."""

    MOD, DEN = 0.02, 0.005
    spatial_inputs, nonspatial_inputs = ["shadow_map"], ["cam"]  # 1 channel, 3 features

    def __init__(self):
        super().__init__()
        self.schedule = DiffusionSchedule()

    def condition(self, spatial, nonspatial):
        time.sleep(self.MOD)
        return None

    def denoiser(self, cond):
        def eps(x, t):
            time.sleep(self.DEN)
            return 0.1 * x
        return eps


@pytest.mark.slow  # asserts wall seconds within 0.3 s of the sleeps: a loaded CPU can break that
def test_timer_counts_the_network_passes():
    cases = speed.random_cases(1, SleepyModel(), 16)
    assert cases[0].source[0].shape == (1, 1, 16, 16) and cases[0].source[1].shape == (1, 3)
    n = 8
    rows, _ = speed.benchmark(SleepyModel(), cases, {"ddim": DDIM}, [n], reference=None, warmup=False)
    (row,) = rows
    assert row["nfe"] == 3 * n and row["records"] == 1
    floor = 2 * SleepyModel.MOD + 3 * n * SleepyModel.DEN  # two Modulator runs + invert, self-decode, decode
    assert floor <= row["time/seconds"] < floor + 0.3  # the slack is other processes on a shared CPU
    rows, _ = speed.benchmark(SleepyModel(), cases, {"ddim": DDIM}, [n], reference=None, warmup=False,
                              mean_matching=False)
    # No self-decode: n fewer passes (40 ms here), measured against the run above rather than a fixed slack.
    assert rows[0]["nfe"] == 2 * n
    assert 2 * SleepyModel.MOD + 2 * n * SleepyModel.DEN <= rows[0]["time/seconds"] < row["time/seconds"]


def test_face_errors_known_values():
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(1, 3, 24, 24, generator=g) * 1.6 - 0.8
    mask = torch.zeros(1, 24, 24, dtype=torch.bool)
    mask[:, 4:20, 6:18] = True
    pred = torch.where(mask[:, None], ref + 0.1, ref)  # 0.1 in [-1, 1] is 0.05 in [0, 1]
    errs = speed.face_errors(pred, ref, mask)
    assert errs["mse"] == pytest.approx(0.05**2, rel=1e-6)
    assert 0 < errs["dssim"] < 0.05
    # The paper's rule (the default) scores SSIM windows on the full images: pixels outside the mask reach the
    # face's border windows, MSE never sees them.
    wild_pred = torch.where(mask[:, None], ref + 0.1, -ref)
    wild = speed.face_errors(wild_pred, ref, mask)
    assert wild["mse"] == pytest.approx(errs["mse"], rel=1e-6) and wild["dssim"] > errs["dssim"]
    assert speed.face_errors(ref, ref, mask) == {"mse": 0.0, "dssim": pytest.approx(0.0, abs=1e-12)}
    assert speed.face_errors(wild_pred, ref, None)["mse"] > errs["mse"]  # no mask: the whole image counts


def _door(model):
    """``model`` behind the relight door (what difareli-bench-samplers builds from a checkpoint)."""
    from difareli.checkpoints.loading import LoadedCheckpoint
    from difareli.relight.relighter import Relighter

    return Relighter(LoadedCheckpoint.of_module(model))


def test_store_cases_target_is_same_subject_other_light(synth_store):
    store = EncodingStore.open(synth_store)
    model = SleepyModel()
    model.spatial_inputs, model.nonspatial_inputs = ["shading", "shadow_map", "masks"], ["shape", "cam", "identity"]
    relighter = _door(model)
    cases = speed.store_cases(store, relighter, records=["s00006_l1", "s00007_l0"], limit=None, oracle_target=True)
    assert [(c.record, c.target) for c in cases] == [("s00006_l1", "s00006_l0"), ("s00007_l0", "s00007_l1")]
    assert cases[0].inputs.startswith("oracle target")
    c = cases[0]
    tgt = store.read("s00006_l0", ["image", "shading", "shadow_map", "masks"])
    src = store.read("s00006_l1", ["masks", "face_mask"])
    np.testing.assert_array_equal(c.target_cond[0][0, :3].permute(1, 2, 0).numpy(), tgt["shading"])
    np.testing.assert_array_equal(c.target_cond[0][0, 3].numpy(), tgt["shadow_map"])
    assert torch.equal(c.target_cond[0][0, 4:], c.source[0][0, 4:])  # masks: the input's
    assert torch.equal(c.target_cond[1], c.source[1])  # shape, cam, identity: the input's
    assert torch.equal(c.mask[0], torch.from_numpy(np.array(src["face_mask"])))
    assert torch.equal(((c.gt[0] + 1) * 127.5).round().byte().permute(1, 2, 0),
                       torch.from_numpy(np.array(tgt["image"])))
    assert len(speed.store_cases(store, relighter, limit=1)) == 1  # default: the test split


def test_store_cases_default_target_is_what_a_user_has(synth_store):
    # Not the target record's stored maps: the light fitted to its image, the policy c, maps re-rendered on
    # the source's geometry (the shadow map ray-marched on the source's depth).
    from difareli.data import target_shadow
    from difareli.render import retarget
    from difareli.lighting.light_fit import LightFit

    store = EncodingStore.open(synth_store)
    model = SleepyModel()
    model.spatial_inputs, model.nonspatial_inputs = ["shading", "shadow_map", "masks"], ["shape", "cam", "identity"]
    c = speed.store_cases(store, _door(model), records=["s00006_l1"], limit=None)[0]
    light = LightFit().from_store(store, "s00006_l0")
    cval, how = target_shadow.target_shadow_of(store, "s00006_l0")
    src = {k: np.asarray(v) for k, v in store.read("s00006_l1").items()}
    np.testing.assert_allclose(c.target_cond[0][0, :3].permute(1, 2, 0).numpy(),
                               retarget.render_shading(src, light), atol=1e-6)
    np.testing.assert_allclose(c.target_cond[0][0, 3].numpy(), retarget.target_shadow_map(src, light, cval), atol=1e-6)
    # This conftest store is inputs=exact: the stored c is exact, so the policy takes the train split's median.
    assert "median shadowed c" in how and how in c.inputs and "fitted" in c.inputs
    assert not np.allclose(light, store.read("s00006_l0", ["light"])["light"], atol=1e-3)  # a fit, not the record's


def test_bench_checkpoint_writes_table_and_plots(tiny_checkpoint, synth_store, tmp_path, capsys):
    cfg = compose(tmp_path, [f"checkpoint={tiny_checkpoint('difareli_pp')}", f"store={synth_store}",
                             "names=[ddim,unipc]", "steps=[2,5]", "reference.steps=5", "limit=1", "warmup=false"])
    out = run(cfg)
    rows = out["rows"]
    assert [(r["sampler"], r["steps"], r["nfe"]) for r in rows] == [("ddim", 2, 6), ("ddim", 5, 15),
                                                                      ("unipc", 2, 6), ("unipc", 5, 15)]
    by = {(r["sampler"], r["steps"]): r for r in rows}
    assert by[("ddim", 5)]["ref/mse"] == 0 and by[("ddim", 5)]["ref/dssim"] == pytest.approx(0, abs=1e-12)
    assert by[("unipc", 5)]["ref/mse"] > 0 and by[("ddim", 2)]["ref/mse"] > 0
    # Two steps: every sampler's steps are first order (no history, last step), so all agree exactly.
    for k in ("ref/mse", "ref/dssim", "gt/mse", "gt/dssim"):
        assert by[("unipc", 2)][k] == by[("ddim", 2)][k]
    assert all(0 < r["gt/mse"] < 1 and 0 < r["gt/dssim"] < 0.5 and r["time/seconds"] > 0 for r in rows)
    table = read_csv(out["paths"]["csv"])
    assert list(table[0]) == ["sampler", "steps", "nfe", "records", "time/seconds", "time/std", "time/targets",
                              "time/end_to_end", "ref/mse", "ref/dssim", "gt/mse", "gt/dssim"]
    # The target shadow map and shading, re-rendered once per case, are the same for every sampler's row.
    assert len({r["time/targets"] for r in rows}) == 1 and rows[0]["time/targets"] > 0
    assert all(r["time/end_to_end"] == pytest.approx(r["time/seconds"] + r["time/targets"]) for r in rows)
    assert float(table[3]["gt/dssim"]) == pytest.approx(rows[3]["gt/dssim"])
    assert iio.imread(out["paths"]["plot"]).ndim == 3
    grid = iio.imread(out["paths"]["grid"])  # 32 px cells enlarged 4x: a head row + one row per sampler
    assert grid.shape[:2] == (3 * (128 + 2) + 2, 3 * (128 + 2) + 2)
    assert "time/seconds" in capsys.readouterr().out


def test_bench_reference_sampler_need_not_be_benchmarked(tiny_checkpoint, synth_store, tmp_path):
    cfg = compose(tmp_path, [f"checkpoint={tiny_checkpoint('difareli_pp')}", f"store={synth_store}",
                             "names=[dpm_solver_pp]", "steps=[3]", "reference.steps=6", "limit=1", "warmup=false"])
    rows = run(cfg)["rows"]
    assert [r["sampler"] for r in rows] == ["dpm_solver_pp"] and rows[0]["ref/mse"] > 0


def test_bench_untrained_preset_timing_only(tmp_path):
    cfg = compose(tmp_path, ["model.preset=tiny", "resolution=32", "names=[ddim,dpm_solver]", "steps=[1,3]",
                             "limit=1"])
    out = run(cfg)
    table = read_csv(out["paths"]["csv"])
    assert list(table[0]) == ["sampler", "steps", "nfe", "records", "time/seconds", "time/std"]
    assert [int(r["nfe"]) for r in table] == [3, 9, 3, 9] and all(float(r["time/seconds"]) > 0 for r in table)
    assert "grid" not in out["paths"] and out["paths"]["plot"].is_file()


def test_bench_bad_configs(tiny_checkpoint, tmp_path):
    with pytest.raises(ValueError, match="store="):
        run(compose(tmp_path, [f"checkpoint={tiny_checkpoint('difareli_pp')}"]))
    with pytest.raises(KeyError, match="heun"):
        run(compose(tmp_path, ["names=[ddim,heun]"]))
    with pytest.raises(ValueError, match="precision"):
        run(compose(tmp_path, ["runtime.precision=fp8"]))


@pytest.mark.slow
def test_console_script_untrained(tmp_path):
    exe = Path(sys.executable).with_name("difareli-bench-samplers")
    res = subprocess.run([str(exe), "model.preset=tiny", "resolution=32", "names=[unipc]", "steps=[2]",
                          "limit=1", "threads=1", "progress=false", f"hydra.run.dir={tmp_path}"], check=True,
                         capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert "unipc" in res.stdout and (tmp_path / "bench_samplers.csv").is_file()
