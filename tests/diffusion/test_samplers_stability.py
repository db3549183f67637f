"""Samplers at the edges: tiny and full step counts, grid ends, bf16 autocast, saturated inputs, callbacks."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from difareli.diffusion import DiffusionSchedule, SamplerConfigError, SamplerSpec

SCHED = DiffusionSchedule()
T = SCHED.T
#: Presets (difareli.diffusion.spec.PRESETS): every sampler and both UniPC variants.
CONFIGS = ("ddim", "dpm_solver", "dpm_solver_pp", "unipc_bh1", "unipc")
#: Max |bf16 - float32| over all samplers at 10 steps (outputs of scale ~1-3), measured: generation 0.0094
#: (dpm_solver), inversion 0.0325 (unipc bh1; inversion amplifies eps errors by sigma'/sigma near the data).
#: Bounds leave ~3x margin.
BF16_BOUND = {"generate": 0.03, "invert": 0.1}



# Small tensors: one intra-op thread (conftest.one_thread) avoids OpenMP spin-waits on a shared CPU.
pytestmark = pytest.mark.usefixtures("one_thread")

class ConvEps(nn.Module):
    """Stands in for the UNet: the optimal eps of N(0, 0.5^2) data plus a small random conv net with a time
    embedding, so trajectories stay image-like. Under autocast it returns the autocast dtype, as a UNet does."""

    def __init__(self, seed: int = 0):
        super().__init__()
        torch.manual_seed(seed)
        self.c1, self.c2 = nn.Conv2d(3, 16, 3, padding=1), nn.Conv2d(16, 3, 3, padding=1)
        self.temb = nn.Linear(2, 16)
        self.register_buffer("abar", torch.as_tensor(SCHED.alphas_cumprod, dtype=torch.float32))
        self.calls: list[tuple[int, torch.dtype]] = []

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        assert t.dtype == torch.long and t.shape == (x.shape[0],) and 0 <= int(t.min()) and int(t.max()) < T
        self.calls.append((int(t[0]), x.dtype))
        ab = self.abar[t].view(-1, 1, 1, 1)
        u = t.float()[:, None] / T * math.pi
        h = torch.nn.functional.silu(self.c1(x) + self.temb(torch.cat([u.sin(), u.cos()], 1))[:, :, None, None])
        out = (1 - ab).sqrt() * x / (0.25 * ab + 1 - ab) + 0.1 * torch.tanh(self.c2(h))
        return out.to(torch.get_autocast_dtype("cpu")) if torch.is_autocast_enabled("cpu") else out


def _run(cfg, model, x, grid, clip_x0=False, **kw):
    with torch.no_grad():
        return SamplerSpec.preset(cfg).run(model, x, grid, SCHED, clip_x0=clip_x0, **kw)


def _x(seed=0, scale=1.0):
    return scale * torch.randn(2, 3, 8, 8, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("cfg", list(CONFIGS))
@pytest.mark.parametrize("n", [1, 2, 3, 7])
@pytest.mark.parametrize("direction", ["generate", "invert"])
@pytest.mark.parametrize("end", ["clean", "t0"])
def test_small_n_and_grid_ends(cfg, n, direction, end):
    model = ConvEps()
    grid = SCHED.time_grid(n, direction=direction, end=end)
    y = _run(cfg, model, _x(n), grid)
    assert y.shape == (2, 3, 8, 8) and y.dtype == torch.float32 and torch.isfinite(y).all()
    # One network call per step, at the current point (the clean end calls t = 0).
    assert [c[0] for c in model.calls] == [max(int(t), 0) for t in grid[:-1]]


@pytest.mark.parametrize("cfg", list(CONFIGS))
def test_one_step_is_ddim_in_closed_form(cfg):
    """A 1-step grid is one DDIM step for every sampler; check it against the formula."""
    model, x = ConvEps(), _x(1)
    a, s, _ = SCHED.marginal(T - 1)
    with torch.no_grad():
        x0 = (x - s * model(x, torch.full((2,), T - 1))) / a
        gen = _run(cfg, model, x, SCHED.time_grid(1))
        torch.testing.assert_close(gen, x0, rtol=1e-5, atol=1e-5)
        eps0 = model(x, torch.zeros(2, dtype=torch.long))
        inv = _run(cfg, model, x, SCHED.time_grid(1, direction="invert"))
        torch.testing.assert_close(inv, a * x + s * eps0, rtol=1e-5, atol=1e-5)
        # Public-code table (abar = 0 at the end): the last inversion step returns x_T = eps.
        inv0 = _run(cfg, model, x, SCHED.time_grid(1, direction="invert", alpha_zero_end=True))
        torch.testing.assert_close(inv0, eps0, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("cfg", list(CONFIGS))
def test_alpha_zero_end_multistep(cfg):
    y = _run(cfg, ConvEps(), _x(2), SCHED.time_grid(7, direction="invert", alpha_zero_end=True))
    assert torch.isfinite(y).all()


@pytest.mark.parametrize("direction", ["generate", "invert"])
def test_ddim_1000_steps(direction):
    y = _run("ddim", ConvEps(), _x(3), SCHED.time_grid(1000, direction=direction))
    assert torch.isfinite(y).all() and y.abs().max() < 10


@pytest.mark.slow
@pytest.mark.parametrize("cfg", [c for c in CONFIGS if c != "ddim"])
@pytest.mark.parametrize("direction", ["generate", "invert"])
def test_multistep_1000_steps(cfg, direction):
    y = _run(cfg, ConvEps(), _x(3), SCHED.time_grid(1000, direction=direction))
    ref = _run("ddim", ConvEps(), _x(3), SCHED.time_grid(1000, direction=direction))
    # At 1000 steps every solver follows the same ODE: close to DDIM.
    assert torch.isfinite(y).all() and (y - ref).abs().max() < 0.05 * ref.abs().max()


def test_bf16_autocast_close_to_float32():
    errs = {}
    for cfg in CONFIGS:
        for direction in ("generate", "invert"):
            grid = SCHED.time_grid(10, direction=direction)
            x = _x(4)
            model = ConvEps()
            ref = _run(cfg, model, x, grid)
            model.calls.clear()
            with torch.autocast("cpu", dtype=torch.bfloat16):
                y = _run(cfg, model, x, grid)
            assert y.dtype == torch.float32 and torch.isfinite(y).all()
            assert all(dt == torch.float32 for _, dt in model.calls)  # the sampler feeds float32; autocast casts
            errs[(cfg, direction)] = float((y - ref).abs().max())
    print("bf16 vs float32 max abs error:", {k: round(v, 4) for k, v in errs.items()})
    for (cfg, direction), err in errs.items():
        assert 0 < err < BF16_BOUND[direction], (cfg, direction, err)


@pytest.mark.parametrize("cfg", list(CONFIGS))
@pytest.mark.parametrize("value", [-1.0, 1.0, -5.0, 5.0, "pm5"])
@pytest.mark.parametrize("clip", [False, True])
def test_extreme_inputs_finite(cfg, value, clip):
    if value == "pm5":
        x = 5.0 * torch.sign(_x(5))
    else:
        x = torch.full((2, 3, 8, 8), value)
    for direction in ("generate", "invert"):
        y = _run(cfg, ConvEps(), x, SCHED.time_grid(10, direction=direction), clip_x0=clip)
        assert torch.isfinite(y).all()
        if clip and direction == "generate":  # the last step lands on x0_hat, clipped
            assert y.abs().max() <= 1.0


def test_clip_rederives_eps():
    """clip_x0 on an inversion step: x' = alpha' clamp(x0_hat) + sigma' (x - alpha clamp(x0_hat)) / sigma."""
    model, x = ConvEps(), _x(6, scale=3.0)
    grid = torch.tensor([100, 400])
    (a, s, _), (a2, s2, _) = SCHED.marginal(100), SCHED.marginal(400)
    with torch.no_grad():
        x0 = ((x - s * model(x, torch.full((2,), 100))) / a).clamp(-1, 1)
        expect = a2 * x0 + s2 * (x - a * x0) / s
        torch.testing.assert_close(_run("ddim", model, x, grid, clip_x0=True), expect)


@pytest.mark.parametrize("cfg", list(CONFIGS))
def test_callback_replaces_x(cfg):
    model, x = ConvEps(), _x(7)
    grid = SCHED.time_grid(6)
    base = _run(cfg, model, x, grid)
    seen = []
    same = _run(cfg, model, x, grid, callback=lambda i, t, tn, y: seen.append((i, t, tn)))
    assert torch.equal(same, base)
    assert seen == [(i, int(grid[i]), int(grid[i + 1])) for i in range(6)]
    shifted = _run(cfg, model, x, grid, callback=lambda i, t, tn, y: y + 0.25 if i == 5 else None)
    torch.testing.assert_close(shifted, base + 0.25)


@pytest.mark.parametrize("variant", ["bh1", "bh2"])
def test_unipc_corrector_keeps_callback_offsets(variant):
    """eps = 0, grid [999, 500, 0], +d after step 0. The corrector rebuilds x_1 from x_0; the callback's
    offset must survive it: x_1 = x_1^c + d, and the last (first-order) step gives
    alpha_0 m_1 + sigma_0 (x_1 - alpha_1 m_1) / sigma_1 with m_1 = (x_1^p + d) / alpha_1, x_1^c - x_1^p = -B d / 2."""
    zero = lambda x, t: torch.zeros_like(x)  # noqa: E731
    x, d = _x(8), 0.1
    (a9, _, l9), (a5, s5, l5), (a0, s0, _) = SCHED.marginal(999), SCHED.marginal(500), SCHED.marginal(0)
    hh = -(l5 - l9)
    B = hh if variant == "bh1" else math.expm1(hh)
    x1p = a5 / a9 * x
    m1 = (x1p + d) / a5
    expect = a0 * m1 + s0 * (-0.5 * B * d) / s5
    y = SamplerSpec.preset("unipc", variant=variant).run(zero, x, [999, 500, 0], SCHED,
                                                         callback=lambda i, t, tn, z: z + d if i == 0 else None)
    torch.testing.assert_close(y, expect, rtol=1e-5, atol=1e-6)


def test_progress_and_registry_errors():
    y = _run("unipc", ConvEps(), _x(9), SCHED.time_grid(3), progress=True)
    assert torch.isfinite(y).all()
    with pytest.raises(SamplerConfigError, match="unknown sampler 'euler'"):
        SamplerSpec(name="euler")
    for bad in ([999, 500, 700, -1], [999, -1, 0], [-1, 1000, 999], [5]):
        with pytest.raises(ValueError):
            _run("ddim", ConvEps(), _x(), bad)
