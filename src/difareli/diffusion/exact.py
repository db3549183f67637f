"""A diffusion whose probability-flow ODE is solvable in closed form, to measure samplers' true errors.

Data ``x0 ~ N(mu, diag(s^2))``. Then ``x_t ~ N(alpha mu, alpha^2 s^2 + sigma^2)`` per dimension (alpha^2 = abar),
the optimal noise prediction is ``eps*(x_t, t) = sigma (x_t - alpha mu) / (alpha^2 s^2 + sigma^2)``, and the
probability-flow ODE keeps ``z = (x_t - alpha_t mu) / sqrt(alpha_t^2 s^2 + sigma_t^2)`` constant: from any
level to any other the exact solution is ``x' = alpha' mu + z sqrt(alpha'^2 s^2 + sigma'^2)``. Feeding eps*
to a sampler therefore measures its discretisation error alone, in either direction.

``gaussian_ode_errors`` runs the whole table (samplers x step counts x directions, plus invert-then-generate
round trips) and ``fit_order`` reads the empirical convergence order off it; ``format_table`` prints it.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from difareli.diffusion.schedule import DiffusionSchedule
from difareli.diffusion.spec import SamplerSpec

#: The presets (``difareli.diffusion.spec.PRESETS``) measured by default: every sampler and UniPC variant.
SAMPLER_CONFIGS: tuple[str, ...] = ("ddim", "dpm_solver", "dpm_solver_pp", "unipc_bh1", "unipc")

DEFAULT_NS = (5, 10, 20, 50, 100, 200, 1000)


class GaussianData:
    """Per-dimension Gaussian data ``N(mu, s^2)`` over a schedule: optimal denoiser and exact flow map."""

    def __init__(self, mu: torch.Tensor, s: torch.Tensor, schedule: DiffusionSchedule):
        self.mu, self.s, self.schedule = mu.double(), s.double(), schedule
        self._abar = torch.as_tensor(schedule.alphas_cumprod, dtype=torch.float64)

    @classmethod
    def random(cls, dim: int, schedule: DiffusionSchedule, seed: int = 0, s_range=(0.1, 0.5)):
        """mu ~ U(-0.5, 0.5), s ~ U(s_range): data inside [-1, 1] like images, some of it sharp."""
        g = torch.Generator().manual_seed(seed)
        mu = torch.rand(dim, generator=g, dtype=torch.float64) - 0.5
        s = s_range[0] + (s_range[1] - s_range[0]) * torch.rand(dim, generator=g, dtype=torch.float64)
        return cls(mu, s, schedule)

    def denoiser(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """eps*(x_t, t) for x of shape (B, dim), computed in float64, returned in x's dtype."""
        ab = self._abar.to(x.device)[t].view(-1, 1)
        mu, s = self.mu.to(x.device), self.s.to(x.device)
        eps = (1 - ab).sqrt() * (x.double() - ab.sqrt() * mu) / (ab * s**2 + 1 - ab)
        return eps.to(x.dtype)

    def _scale(self, abar: float) -> tuple[float, torch.Tensor]:
        return math.sqrt(abar), torch.sqrt(abar * self.s**2 + (1 - abar))

    def sample(self, t: int, batch: int, seed: int = 1) -> torch.Tensor:
        """Exact samples of x_t at grid point t (-1 = clean data), float64, shape (batch, dim)."""
        z = torch.randn(batch, self.mu.numel(), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        a, sd = self._scale(self.schedule.alpha_bar(t))
        return a * self.mu + z * sd

    def flow(self, x: torch.Tensor, t_from: int, t_to: int) -> torch.Tensor:
        """Exact probability-flow map of x from grid point t_from to t_to."""
        a0, sd0 = self._scale(self.schedule.alpha_bar(t_from))
        a1, sd1 = self._scale(self.schedule.alpha_bar(t_to))
        return a1 * self.mu + (x.double() - a0 * self.mu) / sd0 * sd1


def _rel(x: torch.Tensor, ref: torch.Tensor) -> float:
    return float((x.double() - ref).norm() / ref.norm())


def gaussian_ode_errors(samplers: Sequence[str] = tuple(SAMPLER_CONFIGS), ns: Sequence[int] = DEFAULT_NS,
                        directions: Sequence[str] = ("generate", "invert"), grid: str = "uniform",
                        end: str = "clean", schedule: DiffusionSchedule | None = None, dim: int = 256, batch: int = 16,
                        seed: int = 0, dtype: torch.dtype = torch.float64, round_trip: bool = True) -> dict:
    """Relative L2 error of each sampler against the exact ODE solution.

    Returns ``{"errors": {(sampler, direction, n): err}, "round_trip": {(sampler, n): err}}``; direction
    ``"generate"`` maps exact x_{T-1} samples to clean data, ``"invert"`` clean data to x_{T-1}; the round trip
    inverts clean data and generates back with the same grid. ``samplers`` are preset names (``PRESETS``): the
    preset gives the sampler and its options; steps and grids are the table's, and x0 clipping stays off (it
    would mix the clamp's error into the discretisation error measured here).
    ``grid``/``end`` are ``time_grid``'s ``kind``/``end``; with ``end="t0"`` "clean" means t = 0 and n is
    capped at T - 1 (the table keeps the n asked for).
    """
    schedule = schedule or DiffusionSchedule()
    data = GaussianData.random(dim, schedule, seed=seed)
    lo = -1 if end == "clean" else 0
    x_noise, x_clean = data.sample(schedule.T - 1, batch, seed + 1), data.sample(lo, batch, seed + 2)
    grid_of = lambda n, d: schedule.time_grid(min(n, schedule.T - 1 - lo), grid, d, end=end)  # noqa: E731
    errors, trips = {}, {}
    for name in samplers:
        spec = SamplerSpec.preset(name)

        def fn(x: torch.Tensor, g: torch.Tensor, spec: SamplerSpec = spec) -> torch.Tensor:
            return spec.run(data.denoiser, x, g, schedule, clip_x0=False)

        for n in ns:
            inv = None
            for direction in directions:
                g = grid_of(n, direction)
                x = x_noise if direction == "generate" else x_clean
                y = fn(x.to(dtype), g)
                errors[(name, direction, n)] = _rel(y, data.flow(x, int(g[0]), int(g[-1])))
                inv = y if direction == "invert" else inv
            if round_trip:
                inv = inv if inv is not None else fn(x_clean.to(dtype), grid_of(n, "invert"))
                back = fn(inv, grid_of(n, "generate"))
                trips[(name, n)] = _rel(back, x_clean)
    return {"errors": errors, "round_trip": trips}


def fit_order(ns: Sequence[int], errs: Sequence[float]) -> float:
    """Empirical convergence order: minus the least-squares slope of log(err) against log(n)."""
    return -float(np.polyfit(np.log(np.asarray(ns, float)), np.log(np.asarray(errs, float)), 1)[0])


def format_table(result: dict, fit_ns: Sequence[int] | None = None) -> str:
    """A plain-text table: one row per (sampler, direction), errors per n and the fitted order."""
    errors = result["errors"]
    names = list(dict.fromkeys(k[0] for k in errors))
    dirs = list(dict.fromkeys(k[1] for k in errors))
    ns = sorted({k[2] for k in errors})
    fit_ns = [n for n in (fit_ns or ns) if n in ns]
    lines = [f"{'sampler':<15}{'direction':<10}" + "".join(f"{n:>10}" for n in ns) + "     order"]
    for name in names:
        for d in dirs:
            row = [errors[(name, d, n)] for n in ns]
            order = fit_order(fit_ns, [errors[(name, d, n)] for n in fit_ns])
            lines.append(f"{name:<15}{d:<10}" + "".join(f"{e:10.2e}" for e in row) + f"{order:10.2f}")
    for name in names if result["round_trip"] else ():
        row = [result["round_trip"].get((name, n), float("nan")) for n in ns]
        lines.append(f"{name:<15}{'roundtrip':<10}" + "".join(f"{e:10.2e}" for e in row))
    return "\n".join(lines)
