"""Relighting (SPEC 5): conditions prepared once, mean-matching, batching, shadow control, and the extremes.

Each property is checked on a toy model (fast, exact counts) and on the tiny trained checkpoint (the real
network). ``depth_store`` (tests/relight/conftest.py) is the SynthFaces store plus a few extreme input images.
"""

from __future__ import annotations


import numpy as np
import pytest
import torch
from torch import nn

from difareli.data import encodings
from difareli.lighting import sh
from difareli.diffusion.relight import SamplerSpec, decode, invert
from difareli.relight.core import relight
from difareli.diffusion.schedule import DiffusionSchedule
from difareli.data.encodings import normalise_c
from difareli.lit import LoadedCheckpoint, load_checkpoint
from difareli.relight.relighter import Relighter
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets
from difareli.data.inputs import condition_tensors

PP = {"spatial_inputs": ["shading", "shadow_map", "masks"], "nonspatial_inputs": ["shape", "cam", "identity"]}
DR = {"spatial_inputs": ["shading", "background"], "nonspatial_inputs": ["shape", "cam", "identity", "shadow"]}
SAMPLERS = {  # name -> sampler config (conf/sampler/*.yaml keys)
    "ddim": {"name": "ddim"},
    "dpm_solver": {"name": "dpm_solver", "order": 2},
    "dpm_solver_pp": {"name": "dpm_solver_pp", "order": 2},
    "unipc_bh1": {"name": "unipc", "order": 2, "variant": "bh1"},
    "unipc_bh2": {"name": "unipc", "order": 2, "variant": "bh2"},
}
EXTREMES = ("x_black", "x_white", "x_saturated")


def spec(name: str, steps: int, **kw) -> SamplerSpec:
    return SamplerSpec.from_config({**SAMPLERS[name], "steps": steps, **kw})


# ------------------------------------------------------------------------------------------ fixtures
# Small tensors: one intra-op thread (conftest.one_thread) avoids OpenMP spin-waits on a shared CPU.
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def pp_model(tiny_checkpoint) -> LoadedCheckpoint:
    return load_checkpoint(tiny_checkpoint("difareli_pp"))


class ToyModel(nn.Module):
    """``condition``/``denoiser``/``schedule`` like :class:`~difareli.lit.DiffusionModule`, cheap: a conv
    "Modulator" prepares the condition; the denoiser is the optimal eps of N(0, 0.5^2) data plus a small
    condition-dependent conv term, so targets change the result. Records conditions and denoiser batches."""

    def __init__(self, inputs=PP, seed: int = 0):
        super().__init__()
        self.spatial_inputs, self.nonspatial_inputs = list(inputs["spatial_inputs"]), list(inputs["nonspatial_inputs"])
        # Widths from the encoding registry at the producers' dimensions (18 / 184 for DiFaReli++).
        dims = {"H": 32, "W": 32, **encodings.PRODUCER_DIMS}
        spatial_channels = encodings.total_channels(self.spatial_inputs, dims)
        nonspatial_dim = encodings.total_channels(self.nonspatial_inputs, dims)
        torch.manual_seed(seed)
        self.modulator = nn.Conv2d(spatial_channels, 3, 3, padding=1)
        self.ns = nn.Linear(nonspatial_dim, 3)
        self.body = nn.Conv2d(3, 3, 3, padding=1)
        self.schedule = DiffusionSchedule()
        self.register_buffer("abar", torch.as_tensor(self.schedule.alphas_cumprod, dtype=torch.float32))
        self.conditions: list[tuple[torch.Tensor, torch.Tensor]] = []
        self.denoiser_batches: list[int] = []
        self.eval().requires_grad_(False)

    def condition(self, spatial, nonspatial):
        self.conditions.append((spatial.clone(), nonspatial.clone()))
        return torch.tanh(self.modulator(spatial)) + torch.tanh(self.ns(nonspatial))[:, :, None, None]

    def denoiser(self, cond):
        def eps(x, t):
            self.denoiser_batches.append(x.shape[0])
            ab = self.abar[t].view(-1, 1, 1, 1)
            c = cond if cond.shape[0] == x.shape[0] else cond.expand(x.shape[0], -1, -1, -1)
            out = (1 - ab).sqrt() * x / (0.25 * ab + 1 - ab) + 0.2 * torch.tanh(self.body(x) + c)
            return out.to(torch.get_autocast_dtype("cpu")) if torch.is_autocast_enabled("cpu") else out
        return eps


def toy_checkpoint(inputs=PP, seed: int = 0) -> LoadedCheckpoint:
    return LoadedCheckpoint(ToyModel(inputs, seed), dict(inputs), {}, 0)


def toy_inputs(model: ToyModel, b: int = 1, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    sc, nd = model.modulator.in_channels, model.ns.in_features
    return (torch.rand(b, sc, 32, 32, generator=g), torch.randn(b, nd, generator=g))


def toy_image(seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(1, 3, 32, 32, generator=g) * 2 - 1)


class Counter:
    """Counts forward calls (and batch sizes) of a module through a forward hook."""

    def __init__(self, module: nn.Module):
        self.batches: list[int] = []
        self.handle = module.register_forward_hook(lambda m, a, o: self.batches.append(a[0].shape[0]))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.handle.remove()


# ------------------------------------------------------------------------------------------ conditions once
def test_modulator_once_per_condition_toy():
    model = toy_checkpoint().model
    n, b = 5, 3
    with Counter(model.modulator) as mod:
        out = relight(model, toy_image(), toy_inputs(model), toy_inputs(model, b, seed=2), spec("unipc_bh2", n))
    assert out.shape == (b, 3, 32, 32)
    assert mod.batches == [1, b]  # the source once, the target batch once; never per step
    # Inversion + self-decode at batch 1, then one decode of all targets at batch b.
    assert model.denoiser_batches == [1] * (2 * n) + [b] * n


def test_modulator_once_per_condition_checkpoint(pp_model, depth_store):
    store = EncodingStore.open(depth_store)
    r = Relighter(pp_model, {"name": "ddim", "steps": 3}, device="cpu", batch_size=2)
    net = r.model.net
    src = dict(r.source(store, "s00006_l0").arrays)
    lights = sh.yaw(np.asarray(src["light"]), np.linspace(0, 300, 5))
    with Counter(net.spatial) as mod, Counter(net.unet) as unet:
        out = r.relight(r.source(store, "s00006_l0"), Targets.of(lights))
        assert out.shape == (5, 32, 32, 3) and out.dtype == np.uint8
        assert mod.batches == [1, 2, 2, 1]  # source, then ceil(5 / 2) target batches
        assert unet.batches == [1] * 6 + [2] * 3 + [2] * 3 + [1] * 3
        # Second relight of the same record: the cached inversion, only the decode runs.
        r.relight(r.source(store, "s00006_l0"), Targets.of(lights[:2]))
        assert mod.batches[4:] == [2] and unet.batches[15:] == [2] * 3


def test_relighter_caches_inversion_toy(synth_store):
    ckpt = toy_checkpoint(DR)
    store = EncodingStore.open(synth_store)
    r = Relighter(ckpt, {"name": "dpm_solver_pp", "steps": 4, "order": 2}, device="cpu")
    light = np.asarray(store.read("s00006_l1", ["light"])["light"])
    first = r.relight(r.source(store, "s00006_l0"), Targets.of([light]))
    assert ckpt.model.denoiser_batches == [1] * 12  # invert 4 + self-decode 4 + decode 4
    again = r.relight(r.source(store, "s00006_l0"), Targets.of([light, light]))
    assert ckpt.model.denoiser_batches[12:] == [2] * 4  # no inversion the second time
    np.testing.assert_array_equal(again[0], first[0])
    np.testing.assert_array_equal(again[1], first[0])
    r.relight(r.source(store, "s00006_l1"), Targets.of([light]))  # another record is inverted
    assert len(ckpt.model.denoiser_batches) == 12 + 4 + 12


# ------------------------------------------------------------------------------------------ mean-matching
def _inversion_means(denoiser, x0, sp: SamplerSpec, schedule) -> list[torch.Tensor]:
    means = [x0.mean(dim=(2, 3))]
    sp.run(denoiser, x0, sp.grids(schedule)[0], schedule, clip_x0=sp.clip_x0_invert,
           callback=lambda i, t, tn, x: means.append(x.float().mean(dim=(2, 3))))
    return means


def _decode_means(denoiser, inv, schedule) -> list[torch.Tensor]:
    means = []
    decode(denoiser, inv, schedule, callback=lambda i, t, tn, x: means.append(x.float().mean(dim=(2, 3))))
    return means


@pytest.mark.parametrize("name", list(SAMPLERS))
@pytest.mark.parametrize("steps,extra", [(7, {}), (20, {"grid": "logsnr"}), (6, {"alpha_zero_end": True}),
                                         (5, {"clip_x0_invert": True, "clip_x0_generate": True})])
def test_self_decode_reproduces_inversion_means_toy(name, steps, extra):
    model = ToyModel(PP)
    sp = spec(name, steps, **extra)
    den = model.denoiser(model.condition(*toy_inputs(model)))
    x0 = toy_image()
    inv = invert(den, x0, model.schedule, sp)
    assert inv.offsets.shape == (steps, 1, 3)
    want = _inversion_means(den, x0, sp, model.schedule)[::-1][1:]  # decode step i lands on inversion point n-1-i
    got = _decode_means(den, inv, model.schedule)
    assert len(got) == steps
    err = max(float((g - w).abs().max()) for g, w in zip(got, want))
    assert err < 1e-5
    # Not vacuous: the unmatched self-decode drifts from the inversion's means.
    plain = _decode_means(den, invert(den, x0, model.schedule, sp, mean_matching=False), model.schedule)
    drift = max(float((g - w).abs().max()) for g, w in zip(plain, want))
    assert drift > 1e-4 and float(inv.offsets.abs().max()) > 1e-4


@pytest.mark.parametrize("name", ["ddim", "unipc_bh2"])
def test_self_decode_reproduces_inversion_means_checkpoint(name, pp_model, synth_store):
    model = pp_model.model
    r = Relighter(pp_model, {**SAMPLERS[name], "steps": 5}, device="cpu")
    store = EncodingStore.open(synth_store)
    arrays = {k: np.asarray(v) for k, v in store.read("s00006_l0", ["image", *r.model_inputs]).items()}
    den = model.denoiser(model.condition(*condition_tensors(r.model, [arrays])))
    x0 = torch.from_numpy(arrays["image"]).permute(2, 0, 1)[None].float() / 127.5 - 1
    inv = invert(den, x0, model.schedule, r.spec)
    want = _inversion_means(den, x0, r.spec, model.schedule)[::-1][1:]
    err = max(float((g - w).abs().max()) for g, w in zip(_decode_means(den, inv, model.schedule), want))
    assert err < 1e-5 and float(inv.offsets.abs().max()) > 1e-4


# ------------------------------------------------------------------------------------------ batching
def _batched_vs_separate(model, source, targets, x0, sp) -> float:
    inv = invert(model.denoiser(model.condition(*source)), x0, model.schedule, sp)
    b = targets[0].shape[0]
    together = decode(model.denoiser(model.condition(*targets)), inv.expand(b), model.schedule)
    apart = torch.cat([decode(model.denoiser(model.condition(targets[0][i:i + 1], targets[1][i:i + 1])), inv,
                              model.schedule) for i in range(b)])
    return float((together - apart).abs().max())


@pytest.mark.parametrize("name", ["ddim", "unipc_bh2"])
def test_batched_targets_equal_separate_toy(name):
    model = ToyModel(PP)
    assert _batched_vs_separate(model, toy_inputs(model), toy_inputs(model, 4, seed=3), toy_image(),
                                spec(name, 8)) < 1e-5


def test_batched_targets_equal_separate_checkpoint(pp_model, depth_store):
    store = EncodingStore.open(depth_store)
    r = Relighter(pp_model, {"name": "dpm_solver_pp", "steps": 6, "order": 2}, device="cpu")
    arrays = dict(r.source(store, "s00006_l0").arrays)
    from difareli.render.retarget import retarget

    lights = sh.yaw(np.asarray(arrays["light"]), [45.0, 120.0, 250.0])
    targets = condition_tensors(r.model, [retarget(arrays, r.model_inputs, l) for l in lights])
    x0 = torch.from_numpy(np.array(arrays["image"])).permute(2, 0, 1)[None].float() / 127.5 - 1
    assert _batched_vs_separate(pp_model.model, condition_tensors(r.model, [arrays]), targets, x0, r.spec) < 1e-5


# ------------------------------------------------------------------------------------------ shadow control
def test_difareli_shadow_scalar_changes_only_nonspatial(synth_store):
    ckpt = toy_checkpoint(DR)
    store = EncodingStore.open(synth_store)
    r = Relighter(ckpt, {"name": "ddim", "steps": 2}, device="cpu")
    own = np.asarray(store.read("s00006_l0", ["light"])["light"])
    r.relight(r.source(store, "s00006_l0"), Targets.of([own, own, own], [None, -6.0, -1.5]))
    (src_sp, src_ns), (sp, ns) = ckpt.model.conditions
    # The spatial input does not depend on c' (the shading is re-rendered from the normals: float rounding only).
    torch.testing.assert_close(sp, src_sp.expand(3, -1, -1, -1), atol=1e-5, rtol=0)
    assert torch.equal(ns[:, :-1], src_ns[:, :-1].expand(3, -1))  # only the last feature (c) changes
    assert ns[:, -1].tolist() == pytest.approx([float(src_ns[0, -1]), -6.0, -1.5])


def test_difareli_pp_shadow_map_from_target_and_own_map_for_inversion(depth_store):
    ckpt = toy_checkpoint(PP)
    store = EncodingStore.open(depth_store)
    r = Relighter(ckpt, {"name": "ddim", "steps": 2}, device="cpu")
    side = sh.directional_light(np.array([0.7, 0.7, 0.2]) / np.linalg.norm([0.7, 0.7, 0.2]))
    c1, c2 = -4.0, -2.0
    r.relight(r.source(store, "s00006_l0"), Targets.of([side, side], [c1, c2]))
    (src_sp, src_ns), (sp, ns) = ckpt.model.conditions
    stored = torch.from_numpy(np.array(store.read("s00006_l0", ["shadow_map"])["shadow_map"]))
    assert torch.equal(src_sp[0, 3], stored)  # inversion uses the input's own (estimated) map
    assert torch.equal(ns, src_ns.expand(2, -1))  # DiFaReli++: c' does not enter AdaGN
    m1, m2 = sp[0, 3], sp[1, 3]
    assert int((m1 > 0).sum()) > 50 and torch.equal(m1 > 0, m2 > 0)  # the same cast shadow, scaled by c'
    ratio = float(normalise_c(c2) / normalise_c(c1))
    torch.testing.assert_close(m2[m1 > 0] / m1[m1 > 0], torch.full_like(m1[m1 > 0], ratio))
    assert not torch.equal(m1 > 0, stored > 0)  # the target light's shadow, not the input's


# ------------------------------------------------------------------------------------------ extremes: steps
@pytest.mark.parametrize("n", [1, 2, 3, 7])
@pytest.mark.parametrize("name", list(SAMPLERS))
def test_few_steps_relight_toy(name, n):
    model = ToyModel(PP)
    src, tgt = toy_inputs(model), toy_inputs(model, 2, seed=5)
    out = relight(model, toy_image(), src, tgt, spec(name, n))
    # One step from T-1 divides the eps mismatch between two conditions by alpha_{T-1} = 0.0064: the toy's
    # relight is then ~30 in magnitude (clamped in images), but must stay finite and below ~1 / alpha_{T-1}.
    assert torch.isfinite(out).all() and float(out.abs().max()) < 160
    if n == 1 or (n == 2 and name.startswith("dpm")):  # every step is first order here: identical to DDIM
        torch.testing.assert_close(out, relight(model, toy_image(), src, tgt, spec("ddim", n)), atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", ["ddim", pytest.param("dpm_solver", marks=pytest.mark.slow),
                                  pytest.param("dpm_solver_pp", marks=pytest.mark.slow),
                                  pytest.param("unipc_bh2", marks=pytest.mark.slow)])
def test_thousand_steps_relight_toy(name):
    model = ToyModel(PP)
    src = toy_inputs(model)
    x0 = toy_image()
    out = relight(model, x0, src, src, spec(name, 1000))
    # Decoding with the source's own condition returns the input up to the round trip's discretisation error;
    # measured max |error|: ddim 0.0098 (first order: 0.19 at 50 steps, 0.049 at 200), dpm_solver_pp 2.3e-5,
    # unipc 1.5e-4.
    assert torch.isfinite(out).all() and float((out - x0).abs().max()) < (0.02 if name == "ddim" else 1e-3)


@pytest.mark.parametrize("name", ["ddim", "dpm_solver", "dpm_solver_pp", "unipc_bh2"])
def test_few_steps_relight_checkpoint(name, pp_model, depth_store):
    store = EncodingStore.open(depth_store)
    light = np.asarray(store.read("s00006_l1", ["light"])["light"])
    for n in (1, 2, 3, 7) if name in ("ddim", "unipc_bh2") else (1, 3):
        r = Relighter(pp_model, {**SAMPLERS[name], "steps": n}, device="cpu")
        with np.errstate(invalid="raise"):  # a NaN reaching the uint8 conversion raises here
            out = r.relight(r.source(store, "s00006_l0"), Targets.of([light]))
        assert out.shape == (1, 32, 32, 3) and out.dtype == np.uint8 and 20 < out.mean() < 235


#: Max |bf16 autocast - float32| of the relit [-1, 1] image through the tiny network (inversion + self-decode +
#: decode, 10 steps), measured 0.042-0.051 (ddim) and 0.043-0.048 (unipc bh2) depending on the thread count,
#: mean |error| ~0.01. Bound with ~2x margin.
BF16_BOUND = 0.1


@pytest.mark.slow  # two full relights per sampler; bf16 against fp32 stays fast in tests/runtime/test_runtime.py
@pytest.mark.parametrize("name", ["ddim", "unipc_bh2"])
def test_bf16_autocast_matches_float32_checkpoint(name, pp_model, depth_store):
    store = EncodingStore.open(depth_store)
    r = Relighter(pp_model, {**SAMPLERS[name], "steps": 10}, device="cpu")
    arrays = dict(r.source(store, "s00006_l0").arrays)
    model = pp_model.model
    x0 = torch.from_numpy(np.array(arrays["image"])).permute(2, 0, 1)[None].float() / 127.5 - 1
    light = np.asarray(store.read("s00006_l1", ["light"])["light"])
    from difareli.render.retarget import retarget

    args = (model, x0, condition_tensors(r.model, [arrays]),
            condition_tensors(r.model, [retarget(arrays, r.model_inputs, light)]), r.spec)
    ref = relight(*args)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = relight(*args)
    assert low.dtype == torch.float32 and torch.isfinite(low).all()
    err = float((low - ref).abs().max())
    print(f"bf16 vs fp32 {name}: max {err:.4f}, mean {float((low - ref).abs().mean()):.4f}")
    assert err < BF16_BOUND


# ------------------------------------------------------------------------------------------ extremes: inputs
@pytest.mark.parametrize("mean_matching", [True, False])
def test_extreme_images_finite(mean_matching, pp_model, depth_store):
    store = EncodingStore.open(depth_store)
    r = Relighter(pp_model, {"name": "unipc", "order": 2, "variant": "bh2", "steps": 5}, device="cpu",
                  mean_matching=mean_matching)
    model = pp_model.model
    light = np.asarray(store.read("s00006_l1", ["light"])["light"])
    for rid in EXTREMES:
        inv = r.inversion(r.source(store, rid))
        assert torch.isfinite(inv.x_T).all()
        assert inv.offsets is None if not mean_matching else bool(torch.isfinite(inv.offsets).all())
        from difareli.render.retarget import retarget

        arrays = dict(r.source(store, rid).arrays)
        cond = model.condition(*condition_tensors(r.model, [retarget(arrays, r.model_inputs, light)]))
        x = decode(model.denoiser(cond), inv, model.schedule)
        assert torch.isfinite(x).all() and float(x.abs().max()) < 10, rid
        with np.errstate(invalid="raise"):
            out = r.relight(r.source(store, rid), Targets.of([light]))
        assert out.dtype == np.uint8 and out.shape == (1, 32, 32, 3)


def test_extreme_target_lights_finite(pp_model, depth_store):
    store = EncodingStore.open(depth_store)
    r = Relighter(pp_model, {"name": "dpm_solver_pp", "order": 2, "steps": 5}, device="cpu")
    own = np.asarray(dict(r.source(store, "s00006_l0").arrays)["light"], dtype=np.float64)
    negative = own.copy()
    negative[1:4] *= -4.0  # a strong negative lobe: the (unclipped) shading goes negative on one side
    lights = {"zero": np.zeros((9, 3)), "bright10x": 10 * own, "negative_lobe": negative}
    from difareli.render.retarget import retarget

    arrays = dict(r.source(store, "s00006_l0").arrays)
    shading = {k: retarget(arrays, r.model_inputs, l)["shading"] for k, l in lights.items()}
    assert np.abs(shading["zero"]).max() == 0 and shading["negative_lobe"].min() < -0.1
    own_shading = retarget(arrays, r.model_inputs, own)["shading"]
    np.testing.assert_allclose(shading["bright10x"], 10 * own_shading, rtol=1e-5, atol=1e-5)  # linear in the light
    assert all(np.isfinite(v).all() for v in shading.values())
    with np.errstate(invalid="raise"):
        out = r.relight(r.source(store, "s00006_l0"), Targets.of(list(lights.values())))
    assert out.shape == (3, 32, 32, 3) and out.dtype == np.uint8
    # A zero light has no direction: its target shadow map is empty (dominant_direction's frontal fallback).
    assert retarget(arrays, r.model_inputs, lights["zero"])["shadow_map"].max() == 0
