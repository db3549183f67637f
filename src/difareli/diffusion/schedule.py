"""Noise schedule (SPEC 4): float64 tables, the forward process, and the timestep grids samplers walk.

Notation: ``abar_t = prod_{s<=t} (1 - beta_s)`` for integer ``t in {0..T-1}``; ``x_t = alpha_t x0 + sigma_t eps``
with the DPM-Solver quantities of a discrete schedule ``alpha_t = sqrt(abar_t)``, ``sigma_t = sqrt(1 - abar_t)``
and the half log-SNR ``lambda_t = log alpha_t - log sigma_t`` (decreasing in t).

Grid points are integers in ``{-1, 0, ..., T-1, T}``. Two sentinels extend the table, so that a grid can name
its ends exactly (as DDIM's ``alphas_cumprod_prev`` / ``final_alpha_cumprod = 1`` do):

- ``t = -1`` (``CLEAN``): ``abar = 1``, clean data (``sigma = 0``, ``lambda = +inf``).
- ``t = T``: ``abar = 0``, pure noise (``alpha = 0``, ``lambda = -inf``). Only the public-code inversion
  quirk (SPEC 5.3: its table ends at ``abar = 0``, so the last inversion step returns ``x_T = eps``) uses it.

A generation grid of ``n`` steps is ``[T-1 = t_0 > t_1 > ... > t_{n-1} > -1]`` (n + 1 points): the model is
evaluated at ``t_0..t_{n-1}`` and the last step lands on clean data. The inversion grid is its mirror,
``[-1 < t_{n-1} < ... < t_0 = T-1]``: it starts from the clean image and ends at ``T-1``, where generation
starts. Samplers evaluate the network at the current point of each step; at the clean end of an inversion
they call it with ``t = 0`` (the nearest trained level, see ``samplers``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from difareli.errors import UserError

#: Grid sentinel for clean data (abar = 1).
CLEAN = -1

GRID_KINDS = ("uniform", "quadratic", "logsnr")


class DiffusionSchedule:
    """Tables of a discrete DDPM schedule in float64 (numpy and torch) plus grids and ``q_sample``."""

    def __init__(self, T: int = 1000, beta_start: float = 1e-4, beta_end: float = 0.02, kind: str = "linear"):
        if T < 2:
            raise UserError(f"T must be >= 2, got {T}")
        self.T = int(T)
        self.kind = kind
        if kind == "linear":
            betas = np.linspace(beta_start, beta_end, self.T, dtype=np.float64)
        elif kind == "cosine":  # Nichol & Dhariwal (2021), betas capped at 0.999
            f = lambda u: math.cos((u + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
            betas = np.array([min(1 - f((i + 1) / self.T) / f(i / self.T), 0.999) for i in range(self.T)])
        else:
            raise UserError(f"unknown schedule kind {kind!r} (linear | cosine)")
        # Sums of log1p keep 1 - abar accurate near t = 0, where it is ~1e-4 and sigma/lambda depend on it.
        log_ac = np.cumsum(np.log1p(-betas))
        self.betas = betas
        self.alphas_cumprod = np.exp(log_ac)
        self.one_minus_ac = -np.expm1(log_ac)
        self.sqrt_ac = np.sqrt(self.alphas_cumprod)  # alpha_t
        self.sqrt_1m_ac = np.sqrt(self.one_minus_ac)  # sigma_t
        self.log_snr = log_ac - np.log(self.one_minus_ac)  # log(alpha^2 / sigma^2) = 2 lambda_t
        self.lambdas = 0.5 * self.log_snr
        self._dev_cache: dict[torch.device, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}

    # ------------------------------------------------------------------ tables at grid points
    def alpha_bar(self, t: int) -> float:
        """``abar`` at a grid point, sentinels included (-1 -> 1, T -> 0)."""
        t = self._check_point(t)
        return 1.0 if t == CLEAN else 0.0 if t == self.T else float(self.alphas_cumprod[t])

    def marginal(self, t: int) -> tuple[float, float, float]:
        """``(alpha_t, sigma_t, lambda_t)`` as float64 Python floats; +-inf lambda at the sentinels."""
        t = self._check_point(t)
        if t == CLEAN:
            return 1.0, 0.0, math.inf
        if t == self.T:
            return 0.0, 1.0, -math.inf
        return float(self.sqrt_ac[t]), float(self.sqrt_1m_ac[t]), float(self.lambdas[t])

    def _check_point(self, t) -> int:
        t = int(t)
        if not CLEAN <= t <= self.T:
            raise UserError(f"grid point {t} outside [-1, T={self.T}]")
        return t

    # ------------------------------------------------------------------ training side
    def _tables_on(self, device: torch.device):
        if device not in self._dev_cache:
            self._dev_cache[device] = tuple(
                torch.as_tensor(a, dtype=torch.float32, device=device)
                for a in (self.sqrt_ac, self.sqrt_1m_ac, self.alphas_cumprod)
            )
        return self._dev_cache[device]

    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) noise`` per batch element, float32."""
        a, s, _ = self._tables_on(x0.device)
        shape = (-1,) + (1,) * (x0.dim() - 1)
        return a[t].view(shape) * x0.float() + s[t].view(shape) * noise.float()

    def alphas_cumprod_t(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """``abar_t`` per batch element, float32, shaped to broadcast against ``like`` (B, ...)."""
        return self._tables_on(like.device)[2][t].view((-1,) + (1,) * (like.dim() - 1))

    # ------------------------------------------------------------------ sampling grids
    def time_grid(self, n: int, kind: str = "uniform", direction: str = "generate", end: str = "clean",
                  alpha_zero_end: bool = False) -> torch.Tensor:
        """Integer grid of ``n`` steps (``n + 1`` points, long tensor) between ``T-1`` and the clean end ``-1``.

        ``kind`` places the points ``g_k`` (``k = 0..n``, ascending from ``g_0 = -1`` to ``g_n = T-1``):

        - ``uniform``: ``g_k = -1 + k T / n``; equals diffusers' ``"trailing"`` spacing plus the clean end
          (n = 10: 999, 899, ..., 99, -1), and every integer for n = T.
        - ``quadratic``: ``g_k = -1 + (k / n)^2 T`` (DDIM's quadratic, denser near the data).
        - ``logsnr``: the network points ``g_1..g_n`` uniform in lambda from ``lambda_0`` to ``lambda_{T-1}``
          (DPM-Solver's ``logSNR`` skip), so ``g_1 = 0``.

        Points are rounded, then made strictly increasing (each at least one above the previous, room kept
        for the rest), so every ``n`` in ``1..T`` gives exactly ``n`` steps. ``direction="generate"`` returns
        the grid descending, ``"invert"`` ascending. ``end="t0"`` ends the grid at ``t = 0`` instead of clean
        data (``g_0 = 0``, ``-1`` replaced by ``0`` in the formulas above, ``T - 1`` for ``T``, ``n <= T-1``):
        diffusers' ``"linspace"`` spacing with ``final_sigmas_type="sigma_min"`` and its inverse DPM-Solver,
        and a grid whose every point has finite lambda. ``alpha_zero_end`` (inversion only, default off) replaces
        the last point ``T-1`` by ``T`` (abar = 0): the public DiFaReli inversion table (SPEC 5.3).
        """
        n = int(n)
        if end not in ("clean", "t0"):
            raise UserError(f"end must be 'clean' or 't0', got {end!r}")
        g0 = CLEAN if end == "clean" else 0
        span = self.T - 1 - g0  # T for clean ends, T - 1 for t0
        if not 1 <= n <= span:
            raise UserError(f"n must be in [1, {span}], got {n}")
        if kind not in GRID_KINDS:
            raise UserError(f"unknown grid kind {kind!r} ({' | '.join(GRID_KINDS)})")
        if direction not in ("generate", "invert"):
            raise UserError(f"direction must be 'generate' or 'invert', got {direction!r}")
        if alpha_zero_end and direction != "invert":
            raise UserError("alpha_zero_end applies to inversion grids only")
        k = np.arange(n + 1, dtype=np.float64)
        if kind == "uniform":
            f = g0 + k * span / n
        elif kind == "quadratic":
            f = g0 + (k / n) ** 2 * span
        else:
            f = np.empty(n + 1)
            f[0] = g0
            m = n if end == "clean" else n + 1  # lambda-uniform points (the clean end has lambda = inf)
            lam = np.linspace(self.lambdas[0], self.lambdas[-1], m) if m > 1 else self.lambdas[-1:]
            # lambda decreases with t: interpolate t(lambda) on the reversed (increasing) table.
            f[n + 1 - m:] = np.interp(lam, self.lambdas[::-1], np.arange(self.T, dtype=np.float64)[::-1])
        g = np.floor(f + 0.5).astype(np.int64)
        g[0], g[-1] = g0, self.T - 1
        # Sequentially g_k = min(max(g_k, g_{k-1} + 1), T-1-(n-k)): strictly increasing, leaving room for the
        # points after k. In u_k = g_k - k that is a running max of min(u_k, T-1-n).
        ks = np.arange(n + 1)
        g = np.maximum.accumulate(np.minimum(g - ks, self.T - 1 - n)) + ks
        if alpha_zero_end:
            g[-1] = self.T
        return torch.from_numpy(g if direction == "invert" else g[::-1].copy())
