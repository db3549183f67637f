"""The inference runtime on CPU: config validation, bf16 and compiled relights against fp32 eager, the CUDA-graph
fallback, timing and FLOP counting. ``tests/runtime/test_gpu.py`` runs the same relight checks on CUDA."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from difareli.diffusion.relight import SamplerSpec, decode, invert
from difareli.diffusion.schedule import DiffusionSchedule
from difareli.data.encodings import channels
from difareli.hardware import _cpu_peak, peak_flops
from difareli.runtime.core import Runtime, _flatten, count_flops

# Relight agreement tolerances, as relative L2 errors ||out - ref|| / ||ref|| (see rel_error) of a 10-step DDIM
# invert + self-decode + batched decode of a random tiny network at 32 px. Its eps is uncorrelated with x_t, so
# decoded pixels are far outside [-1, 1] (max ~170) and absolute differences mean little. bf16 keeps 8 mantissa
# bits: measured 0.024 on CPU (eps itself differs by ~2.5% per pass). Compile and graphs reorder float32 sums only.
BF16_TOL = 0.08
COMPILE_TOL = 1e-4
RES = 32
SPATIAL = ("shading", "shadow_map", "masks")
NONSPATIAL = ("shape", "cam", "identity")
DIMS = {"H": RES, "W": RES, "S": 53, "D": 128}  # SynthFaces' shape and identity lengths


def random_network(device: str | torch.device = "cpu", seed: int = 0):
    """An untrained tiny DiFaReli++ network whose zero-initialised output layers are re-initialised, so eps is not
    identically 0 (the comparisons below would otherwise pass trivially)."""
    from difareli.nn import build_network

    torch.manual_seed(seed)
    net = build_network("tiny", "modulator", sum(channels(n, DIMS) for n in SPATIAL),
                        sum(channels(n, DIMS) for n in NONSPATIAL), overrides={"image_size": RES})
    for m in net.modules():
        if isinstance(m, (torch.nn.Conv1d, torch.nn.Conv2d)) and not m.weight.any():
            m.reset_parameters()
    return net.to(device).eval().requires_grad_(False)


def relight_inputs(net, device: str | torch.device = "cpu", targets: int = 2, seed: int = 1):
    """``(x0 [1,3,R,R], source (spatial, nonspatial), targets (spatial, nonspatial) with batch ``targets``)``."""
    g = torch.Generator().manual_seed(seed)
    sc = sum(channels(n, DIMS) for n in SPATIAL)

    def cond(b):
        return (torch.rand(b, sc, RES, RES, generator=g).to(device),
                torch.randn(b, net.nonspatial_dim, generator=g).to(device))

    return (torch.rand(1, 3, RES, RES, generator=g) * 2 - 1).to(device), cond(1), cond(targets)


@torch.no_grad()
def relight_with(runtime: Runtime, net, x0, source, targets, spec: SamplerSpec | None = None) -> torch.Tensor:
    """invert (+ mean-matching self-decode) with the source condition, then one batched decode of the targets."""
    spec = spec or SamplerSpec(name="ddim", steps=10)
    schedule = DiffusionSchedule()
    inv = invert(runtime.denoiser(net, net.condition(*source)), x0, schedule, spec)
    n = targets[1].shape[0]
    return decode(runtime.denoiser(net, net.condition(*targets)), inv.expand(n), schedule)


def rel_error(out: torch.Tensor, ref: torch.Tensor) -> float:
    return ((out.double() - ref.double()).norm() / ref.double().norm()).item()


@pytest.fixture(scope="module")
def case(one_thread):
    net = random_network()
    x0, src, tgt = relight_inputs(net)
    return net, x0, src, tgt, relight_with(Runtime(device="cpu", precision="fp32"), net, x0, src, tgt)


# ---------------------------------------------------------------------- configuration
def test_from_config_defaults_and_values():
    assert Runtime.from_config(None) == Runtime()
    rt = Runtime.from_config({"device": "cpu", "precision": "bf16", "compile": True, "cuda_graphs": False})
    assert (rt.torch_device, rt.dtype, rt.lightning_precision) == (torch.device("cpu"), torch.bfloat16, "bf16-mixed")


def test_default_yaml_matches_the_dataclass():
    from omegaconf import OmegaConf

    from difareli.configs import CONFIG_DIR

    cfg = OmegaConf.load(CONFIG_DIR / "runtime" / "default.yaml")
    assert Runtime.from_config(cfg) == Runtime()


@pytest.mark.parametrize("cfg, words", [
    ({"precison": "bf16"}, "precison"),
    ({"precision": "fp8"}, "runtime.precision='fp8'"),
    ({"device": "gpu"}, "runtime.device='gpu'"),
    ({"compile": "yes"}, "runtime.compile='yes'"),
    ({"cuda_graphs": 1}, "runtime.cuda_graphs=1"),
])
def test_bad_config_names_the_key(cfg, words):
    with pytest.raises(ValueError, match=words.replace("[", r"\[").replace(".", r"\.")):
        Runtime.from_config(cfg)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the CPU-only errors")
def test_cpu_only_errors():
    with pytest.raises(ValueError, match="fp16 needs CUDA"):
        Runtime(device="cpu", precision="fp16")
    with pytest.raises(ValueError, match="CUDA is not available"):
        Runtime(device="cuda")


# ---------------------------------------------------------------------- relights on CPU
def test_fp32_denoiser_is_the_network(case):
    net, x0, src, *_ = case
    cond = net.condition(*src)
    t = torch.tensor([500])
    with torch.no_grad():
        eps = Runtime(device="cpu", precision="fp32").denoiser(net, cond)(x0, t)
        assert torch.equal(eps, net(x0, t, cond))
    assert eps.abs().mean() > 0.05  # re-initialised: a zero network would make every comparison trivial


def test_bf16_relight_agrees_with_fp32(case):
    net, x0, src, tgt, ref = case
    cond = net.condition(*src)
    with torch.no_grad():
        eps = Runtime(device="cpu", precision="bf16").denoiser(net, cond)(x0, torch.tensor([500]))
    assert eps.dtype == torch.float32
    out = relight_with(Runtime(device="cpu", precision="bf16"), net, x0, src, tgt)
    assert out.dtype == torch.float32 and out.shape == ref.shape == (2, 3, RES, RES)
    assert 1e-4 < rel_error(out, ref) < BF16_TOL  # > 1e-4: autocast really ran in bf16


def test_cuda_graphs_fall_back_to_eager_on_cpu(case):
    net, x0, src, tgt, ref = case
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = relight_with(Runtime(device="cpu", precision="fp32", cuda_graphs=True), net, x0, src, tgt)
    assert torch.equal(out, ref)
    assert any("cuda_graphs" in str(w.message) for w in caught)


@pytest.mark.slow  # inductor on this shared CPU: minutes per compile
def test_compiled_relight_agrees_with_eager(case):
    net, x0, src, tgt, ref = case
    out = relight_with(Runtime(device="cpu", precision="fp32", compile=True), net, x0, src, tgt)
    assert rel_error(out, ref) < COMPILE_TOL


# ---------------------------------------------------------------------- pieces
def test_condition_flattens_to_its_tensors(case):
    import torch.utils._pytree as pytree

    net, x0, src, *_ = case
    cond = net.condition(*src)
    leaves, spec = _flatten(cond)
    assert len(leaves) == len(cond.spatial) + 1 and all(torch.is_tensor(v) for v in leaves)
    back = pytree.tree_unflatten(leaves, spec)
    assert type(back) is type(cond) and back.nonspatial is cond.nonspatial and back.spatial[0] is cond.spatial[0]


@pytest.mark.slow  # asserts a 50 ms sleep reads under 1 s of wall time: not on a loaded CPU
def test_timed_measures_a_sleep():
    import time

    with Runtime(device="cpu").timed() as t:
        time.sleep(0.05)
    assert 0.05 <= t.seconds < 1.0


def test_count_flops_of_a_linear_layer():
    lin = torch.nn.Linear(16, 8)
    assert count_flops(lin, torch.randn(4, 16)) == 2 * 4 * 16 * 8


def test_cpu_peak_is_positive_and_bf16_not_slower():
    fp32, how = peak_flops("cpu", "fp32")
    bf16, _ = peak_flops("cpu", "bf16")
    if fp32 is None:
        pytest.skip(how)
    assert math.isfinite(fp32) and fp32 > 1e9 and bf16 >= fp32 and "MHz" in how


def _cpuinfo(vendor: str, family: int, flags: str) -> str:
    return (f"processor\t: 0\nvendor_id\t: {vendor}\ncpu family\t: {family}\ncpu MHz\t\t: 2000.000\n"
            f"flags\t\t: fpu sse2 avx2 fma {flags}\n")


@pytest.mark.parametrize("vendor, family, flags, fp32_per_cycle, bf16_per_cycle", [
    ("AuthenticAMD", 25, "avx512f avx512_bf16", 32, 64),  # Zen 4: AVX-512 on 256-bit pipes
    ("GenuineIntel", 6, "avx512f avx512_bf16", 64, 128),  # two 512-bit FMA pipes
    ("GenuineIntel", 6, "avx512f avx512_bf16 amx_bf16 amx_tile", 64, 1024),  # AMX: 1,024 bf16 FLOP/cycle/core
    ("GenuineIntel", 6, "", 32, 32),  # AVX2 only: bf16 runs at most at the fp32 rate
])
def test_cpu_peak_per_instruction_set(vendor, family, flags, fp32_per_cycle, bf16_per_cycle):
    info = _cpuinfo(vendor, family, flags)
    fp32, _ = _cpu_peak("fp32", info, cores=2)
    bf16, how = _cpu_peak("bf16", info, cores=2)
    assert fp32 == 2 * 2000e6 * fp32_per_cycle and bf16 == 2 * 2000e6 * bf16_per_cycle
    assert ("AMX" in how) == ("amx_bf16" in flags)
    assert _cpu_peak("fp16", info, cores=2)[0] <= 2 * 2000e6 * max(bf16_per_cycle, fp32_per_cycle)
