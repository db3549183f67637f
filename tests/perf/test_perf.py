"""difareli.perf.measure: variant configs composed without Hydra, untrained models equal to Hydra-built ones, random
inputs of their shapes, timing, and the benchmark scripts built on them (bench_train, ablation_report)."""

from __future__ import annotations

import functools
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import hydra
import pytest
import torch
from omegaconf import OmegaConf

from difareli.data import encodings
from difareli.perf import measure as perf
from difareli.configs import CONFIG_DIR

from tests.helpers import compose_train

pytestmark = pytest.mark.usefixtures("one_thread")
ROOT = Path(__file__).resolve().parents[2]
# Every model variant: the top-level files and the Table II / IV rows (spatial/, nonspatial/, scheduler/ are options).
VARIANTS = [p.stem for p in sorted((CONFIG_DIR / "model").glob("*.yaml"))] + [
    f"{g}/{p.stem}" for g in ("mechanism", "ablation") for p in sorted((CONFIG_DIR / "model" / g).glob("*.yaml"))]


def hydra_model_config(tmp_path: Path, variant: str) -> dict:
    cfg = compose_train(tmp_path, [f"model={variant}"])
    return OmegaConf.to_container(cfg.model, resolve=True)


def hydra_model(cfg: dict, preset: str, res: int):
    """The model as Hydra instantiates it (difareli-bench-samplers did so before difareli.perf.measure)."""
    dims = {"H": res, "W": res, **encodings.PRODUCER_DIMS}
    sizes = {"spatial_channels": encodings.total_channels(cfg["spatial_inputs"], dims),
             "nonspatial_dim": encodings.total_channels(cfg["nonspatial_inputs"], dims), "resolution": res}
    torch.manual_seed(0)
    return hydra.utils.instantiate({k: v for k, v in cfg.items() if k != "preset"}, preset=preset, input_dims=sizes)


def load_script(name: str):
    spec = importlib.util.spec_from_file_location(f"script_{name}", ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("variant", VARIANTS)
def test_variant_config_is_what_hydra_composes(variant, tmp_path):
    assert len(VARIANTS) >= 13
    assert perf.variant_config(variant) == hydra_model_config(tmp_path, variant)


@pytest.mark.parametrize("variant", ["difareli_pp", "difareli", "mechanism/cn_ca", "ablation/concat", "student"])
def test_built_model_equals_the_hydra_instantiated_one(variant, tmp_path):
    cfg = hydra_model_config(tmp_path, variant)
    ref = hydra_model(cfg, "tiny", 32)
    built = perf.build_model(variant, "tiny", 32)
    n = sum(p.numel() for p in built.parameters())
    assert n == sum(p.numel() for p in ref.parameters()) and n > 100_000
    assert type(built) is type(ref) and dict(built.hparams) == dict(ref.hparams)
    a, b = built.state_dict(), ref.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)  # same seed, same weights


def test_build_model_options_preset_and_plain_optimizer():
    m = perf.build_model("difareli", "tiny", compile=False)  # resolution: the preset's image size
    # shading 3 + background 3 channels; shape 53, cam 3, identity 128, shadow 1 features
    assert m.hparams.input_dims == {"spatial_channels": 6, "nonspatial_dim": 53 + 3 + 128 + 1, "resolution": 32}
    assert isinstance(m._optimizer, functools.partial)  # trains through Lightning without Hydra
    opt = m.configure_optimizers()
    assert type(opt) is torch.optim.AdamW and opt.defaults["lr"] == 1e-4 and opt.defaults["weight_decay"] == 0.0
    model, res = perf.untrained_model("difareli", "tiny", 16)
    assert res == 16 and not model.training and not any(p.requires_grad for p in model.parameters())


def test_random_condition_shapes_and_seeding():
    m = perf.build_model("difareli_pp", "tiny", 16)
    sp, ns = perf.random_condition(m, 3, 16, seed=7)
    assert sp.shape == (3, 3 + 1 + 14, 16, 16) and ns.shape == (3, 53 + 3 + 128)  # shading, shadow map, masks
    assert 0 <= sp.min() and sp.max() < 1 and ns.std() > 0.5  # uniform maps, normal vectors
    again = perf.random_condition(m, 3, 16, seed=7)
    assert torch.equal(sp, again[0]) and torch.equal(ns, again[1])
    g = torch.Generator().manual_seed(7)
    first, second = perf.random_condition(m, 1, 16, generator=g), perf.random_condition(m, 1, 16, generator=g)
    assert not torch.equal(first[0], second[0])  # one generator: successive draws differ
    no_vector = SimpleNamespace(spatial_inputs=["shading"], nonspatial_inputs=[])
    assert perf.random_condition(no_vector, 1, 8)[1] is None


def test_random_batch_and_train_step_flops():
    m = perf.build_model("difareli_pp", "tiny", 16)
    batch = perf.random_batch(m, 2)
    assert batch["image"].shape == (2, 3, 16, 16) and batch["spatial"].shape == (2, 18, 16, 16)
    assert batch["nonspatial"].shape == (2, 184) and -1 <= batch["image"].min() < 0 < batch["image"].max() <= 1
    assert torch.equal(batch["image"][1], perf.RandomBatches.of(m, 2)[1]["image"])
    assert perf.train_step_flops(m, batch) > 0 and all(p.grad is None for p in m.parameters())


def test_time_calls_runs_warmup_untimed():
    calls = []

    def fn():
        calls.append(1)
        time.sleep(0.01)

    t = perf.time_calls(fn, 3, warmup=2)
    assert len(calls) == 5 and len(t.wall) == len(t.cpu) == 3
    assert t.best >= 0.01 and t.median >= t.best and "ms wall" in t.median_ms()


def test_gemm_ceiling_is_2n3_over_the_fastest_timed_matmul(monkeypatch):
    # A fake clock: the warm-up matmul "takes" 0.5 s, the timed ones 2, 1 and 3 s. The ceiling must skip the
    # warm-up (else 2 n^3 / 0.5) and take the fastest timed one (else 2 n^3 / 2 for the mean).
    durations = iter([0.5, 2.0, 1.0, 3.0])
    clock = {"t": 0.0, "start": True}

    def fake():
        if not clock["start"]:
            clock["t"] += next(durations)
        clock["start"] = not clock["start"]
        return clock["t"]

    monkeypatch.setattr(perf, "time", SimpleNamespace(perf_counter=fake))  # perf's clock only
    assert perf.gemm_ceiling("cpu", "fp32", n=32, repeats=3) == 2 * 32 ** 3 / 1.0
    monkeypatch.undo()
    assert perf.gemm_ceiling("cpu", "bf16", n=64, repeats=2) > 0


@pytest.mark.slow  # a fresh interpreter runs scripts/bench_train.py: ~13 s loaded (profile_train_step stays fast)
def test_bench_train_script_reports_the_built_models_parameters():
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_train.py"), "--configs", "tiny:16:2:32-true",
                           "--steps", "1", "--warmup", "1", "--variant", "difareli", "--json", "/dev/stdout"],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"},
                          check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    row = json.loads(proc.stdout[proc.stdout.index("[\n"):])[0]
    built = perf.build_model("difareli", "tiny", 16)
    assert row["params_M"] == round(sum(p.numel() for p in built.parameters()) / 1e6, 2)
    assert row["images_per_s"] > 0 and row["step_GFLOP"] > 0


@pytest.mark.slow  # a profiled training step: the default run has to finish in minutes at load 4
def test_profile_train_step_accounts_for_the_step():
    """Every category is a share of the profiled step: convolutions are there, nothing is negative, and the self
    times add up to no more than the threads could spend in the wall time (and to a good share of it)."""
    # The operators' share of the wall step is a property of the host, not of the accounting: 0.73-0.79 with two
    # free threads, 0.50 and 0.497 under this test on a host stealing ~40% of the CPU (a fail at the old 0.5
    # bound, in a clean-clone run and one of three reruns). The bound below only catches a category set that
    # misses most of the work.
    prof = perf.profile_train_step("tiny", 16, 2, "32-true", steps=3, warmup=1)
    parts = prof.seconds
    assert set(parts) == {*perf.STEP_CATEGORIES, "other"} and prof.total == pytest.approx(sum(parts.values()))
    assert prof.conv_gflops > 0 and prof.gemm_gflops > 0
    assert all(v >= 0 for v in parts.values()) and parts["convolution"] > 0 and parts["optimizer (AdamW)"] > 0
    assert 0.3 * prof.step < prof.total <= 1.05 * prof.step


class _OneConv(torch.nn.Module):
    """A module whose loss is one 3x3 convolution: its FLOPs in closed form."""

    def __init__(self, image_grad: bool):
        super().__init__()
        self.conv, self.image_grad = torch.nn.Conv2d(3, 8, 3, padding=1), image_grad

    def diffusion_loss(self, batch):
        x = batch["x"].requires_grad_(self.image_grad)
        return self.conv(x).square().mean() + x.sum() * 0  # a pointwise op, not counted


@pytest.mark.parametrize("image_grad", [False, True])
@pytest.mark.parametrize("bf16", [False, True])
def test_train_step_flops_counts_the_convolutions_forward_and_backward(image_grad, bf16):
    """2 B C_out H W C_in k^2 forward; the weight's gradient as much again, and the input's where it is asked for;
    under bf16 autocast the same count."""
    fwd = 2 * 2 * 8 * 8 * 8 * 3 * 9
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        got = perf.train_step_flops(_OneConv(image_grad), {"x": torch.randn(2, 3, 8, 8)}, "convolution")
    assert got == fwd * (3 if image_grad else 2)


def test_ablation_report_counts_every_pass():
    report = load_script("ablation_report")
    plain = report.measured_costs(perf.variant_config("difareli_pp"), steps=2, repeats=1)
    controlnet = report.measured_costs(perf.variant_config("mechanism/cn_ca"), steps=2, repeats=1)
    # DDIM with mean-matching: inversion, self-decode, decode = 3 passes per step; one condition per side.
    assert {k: plain[k] for k in ("unet", "controlnet", "condition")} == {"unet": 6, "controlnet": 0, "condition": 2}
    assert controlnet["controlnet"] == 6 and controlnet["seconds"] > 0
