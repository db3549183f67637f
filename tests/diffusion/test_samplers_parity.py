"""Our samplers against diffusers' schedulers (the oracle), on the same grid, with a toy eps-model.

diffusers keeps float32 tables; we overwrite them with our float64 ones so the comparison separates the
algorithm from table rounding, and run everything in float64 (diffusers' DPMSolverMultistepScheduler still
downcasts the sample to float32 inside ``step``: its comparisons carry float32 rounding).
Grids: diffusers' ``"trailing"`` spacing + the clean end is our ``uniform`` grid; its ``"linspace"`` spacing
with ``final_sigmas_type="sigma_min"`` (required for noise-prediction DPM-Solver) and its inverse
DPM-Solver's grid are our ``uniform`` grid with ``end="t0"``.
"""

from __future__ import annotations

import math

import pytest
import torch

diffusers = pytest.importorskip("diffusers")

from difareli.diffusion import DiffusionSchedule, SamplerSpec  # noqa: E402

SCHED = DiffusionSchedule()
T = SCHED.T
NS = (5, 10, 50)
TOL = 1e-5



# Small tensors: one intra-op thread (conftest.one_thread) avoids OpenMP spin-waits on a shared CPU.
pytestmark = pytest.mark.usefixtures("one_thread")

class ToyEps:
    """eps(x, t) = channel mix of x + a smooth per-channel function of t (deterministic, any dtype)."""

    def __init__(self, channels: int = 3, seed: int = 0):
        g = torch.Generator().manual_seed(seed)
        self.w = 0.5 * torch.eye(channels, dtype=torch.float64) + 0.2 * torch.randn(channels, channels, generator=g,
                                                                                      dtype=torch.float64)
        self.phase = torch.rand(channels, generator=g, dtype=torch.float64) * 6.0
        self.calls: list[int] = []

    def __call__(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        assert t.dtype == torch.long and t.shape == (x.shape[0],)
        self.calls.append(int(t[0]))
        tt = t.to(torch.float64).view(-1, 1)
        bias = 0.3 * torch.cos(tt * math.pi / T + self.phase)  # (B, C)
        out = torch.einsum("ij,bjhw->bihw", self.w.to(x.dtype), x) + bias.to(x.dtype)[:, :, None, None]
        return out


def _x(seed: int) -> torch.Tensor:
    return torch.randn(2, 3, 4, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def _sigmas64(ts) -> torch.Tensor:
    """diffusers' sigma = sqrt((1 - abar) / abar) at grid points (clean end -> 0), float64."""
    return torch.tensor([0.0 if t == -1 else math.sqrt(SCHED.one_minus_ac[t] / SCHED.alphas_cumprod[t])
                         for t in ts], dtype=torch.float64)


def _f64_tables(sched):
    ac = torch.from_numpy(SCHED.alphas_cumprod.copy())
    sched.alphas_cumprod = ac
    for name, arr in (("alpha_t", SCHED.sqrt_ac), ("sigma_t", SCHED.sqrt_1m_ac), ("lambda_t", SCHED.lambdas)):
        if hasattr(sched, name):
            setattr(sched, name, torch.from_numpy(arr.copy()))
    return sched


def _run(preset: str, model, x: torch.Tensor, grid, **options) -> torch.Tensor:
    """The preset (its options overridden) over ``grid``: every sampler is run through SamplerSpec."""
    return SamplerSpec.preset(preset, **options).run(model, x, grid, SCHED)


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max())


def _diffusers_loop(sched, model, x, eval_ts, step_ts):
    for te, ts in zip(eval_ts, step_ts):
        eps = model(x, torch.full((x.shape[0],), max(te, 0), dtype=torch.long))
        x = sched.step(eps, ts, x).prev_sample.to(torch.float64)
    return x


@pytest.mark.parametrize("n", NS)
def test_ddim_generation_matches_diffusers(n):
    sched = _f64_tables(diffusers.DDIMScheduler(clip_sample=False, set_alpha_to_one=True,
                                                timestep_spacing="trailing"))
    sched.final_alpha_cumprod = torch.tensor(1.0, dtype=torch.float64)
    sched.set_timesteps(n)
    grid = SCHED.time_grid(n)
    assert sched.timesteps.tolist() + [-1] == grid.tolist()
    model, x = ToyEps(), _x(1)
    ref = _diffusers_loop(sched, model, x, sched.timesteps.tolist(), sched.timesteps.tolist())
    ours = _run("ddim", model, x, grid)
    assert ours.dtype == torch.float64
    assert _rel(ours, ref) < TOL


@pytest.mark.parametrize("n", NS)
def test_ddim_inversion_matches_diffusers(n):
    sched = _f64_tables(diffusers.DDIMInverseScheduler(clip_sample=False, set_alpha_to_one=True,
                                                       timestep_spacing="trailing"))
    sched.initial_alpha_cumprod = torch.tensor(1.0, dtype=torch.float64)
    sched.set_timesteps(n)
    grid = SCHED.time_grid(n, direction="invert")
    assert [-1] + sched.timesteps.tolist() == grid.tolist()
    model, x = ToyEps(), _x(2)
    # diffusers' step(eps, t, x) moves from t - T/n to t; we evaluate eps at the current point (t=0 at the
    # clean end), so the oracle is fed exactly that.
    ref = _diffusers_loop(sched, model, x, grid.tolist()[:-1], sched.timesteps.tolist())
    model.calls.clear()
    ours = _run("ddim", model, x, grid)
    assert model.calls == [0] + grid.tolist()[1:-1]
    assert _rel(ours, ref) < TOL


def _dpm(algorithm: str, final: str, spacing: str):
    return _f64_tables(diffusers.DPMSolverMultistepScheduler(
        algorithm_type=algorithm, solver_order=2, solver_type="midpoint", lower_order_final=True,
        final_sigmas_type=final, timestep_spacing=spacing))


@pytest.mark.parametrize("n", NS)
@pytest.mark.parametrize("algorithm,name,final", [("dpmsolver++", "dpm_solver_pp", "zero"),
                                                  ("dpmsolver++", "dpm_solver_pp", "sigma_min"),
                                                  ("dpmsolver", "dpm_solver", "sigma_min")])
def test_dpm_solver_generation_matches_diffusers(n, algorithm, name, final):
    # diffusers refuses final_sigmas_type="zero" for noise prediction; ours allows it (first-order last step).
    sched = _dpm(algorithm, final, "trailing" if final == "zero" else "linspace")
    sched.set_timesteps(n)
    grid = SCHED.time_grid(n) if final == "zero" else SCHED.time_grid(n, end="t0")
    assert sched.timesteps.tolist() == grid.tolist()[:-1]
    sched.sigmas = _sigmas64(grid.tolist())
    model, x = ToyEps(), _x(3)
    ref = _diffusers_loop(sched, model, x, sched.timesteps.tolist(), sched.timesteps.tolist())
    ours = _run(name, model, x, grid)
    assert _rel(ours, ref) < TOL


@pytest.mark.parametrize("n", NS + (20,))
@pytest.mark.parametrize("algorithm,name", [("dpmsolver++", "dpm_solver_pp"), ("dpmsolver", "dpm_solver")])
def test_dpm_solver_inversion_matches_diffusers(n, algorithm, name):
    # n = 20 >= 15: diffusers keeps the last step second order; so must we.
    sched = _f64_tables(diffusers.DPMSolverMultistepInverseScheduler(
        algorithm_type=algorithm, solver_order=2, solver_type="midpoint", lower_order_final=True))
    sched.set_timesteps(n)
    grid = SCHED.time_grid(n, direction="invert", end="t0")
    assert sched.timesteps.tolist() == grid.tolist()[:-1]
    sched.sigmas = _sigmas64(grid.tolist())
    model, x = ToyEps(), _x(4)
    ref = _diffusers_loop(sched, model, x, sched.timesteps.tolist(), sched.timesteps.tolist())
    ours = _run(name, model, x, grid)
    assert _rel(ours, ref) < TOL
    # Guard against a vacuous pass: order 1 (DDIM) on the same grid differs clearly.
    assert _rel(_run("ddim", model, x, grid), ref) > 1e-3


@pytest.mark.parametrize("n", NS)
@pytest.mark.parametrize("variant,final", [("bh2", "zero"), ("bh2", "sigma_min"), ("bh1", "sigma_min")])
def test_unipc_generation_matches_diffusers(n, variant, final):
    # diffusers' bh1 with final_sigmas_type="zero" returns NaN (B(h) = -h is infinite on the last step and is
    # multiplied by a zero residual); ours stays finite there (tests/diffusion/test_samplers_stability.py), and bh1 is
    # compared on the t0-ended grid.
    sched = _f64_tables(diffusers.UniPCMultistepScheduler(
        solver_order=2, solver_type=variant, predict_x0=True, lower_order_final=True, final_sigmas_type=final,
        timestep_spacing="trailing" if final == "zero" else "linspace"))
    sched.set_timesteps(n)
    grid = SCHED.time_grid(n) if final == "zero" else SCHED.time_grid(n, end="t0")
    assert sched.timesteps.tolist() == grid.tolist()[:-1]
    sched.sigmas = _sigmas64(grid.tolist())
    model, x = ToyEps(), _x(5)
    ref = _diffusers_loop(sched, model, x, sched.timesteps.tolist(), sched.timesteps.tolist())
    ours = _run("unipc", model, x, grid, variant=variant)
    assert _rel(ours, ref) < TOL
    # The corrector matters (it is what the oracle checks beyond DPM-Solver++).
    no_corr = _run("unipc", model, x, grid, variant=variant, corrector=False)
    assert _rel(no_corr, ref) > 1e-4


def test_parity_float32_close():
    """Float32 inputs stay float32 and agree with the float64 run to float32 accuracy."""
    model, x = ToyEps(), _x(6)
    grid = SCHED.time_grid(10)
    for name in ("ddim", "dpm_solver", "dpm_solver_pp", "unipc"):
        y32 = _run(name, model, x.float(), grid)
        y64 = _run(name, model, x, grid)
        assert y32.dtype == torch.float32
        assert _rel(y32.double(), y64) < 1e-5, name
