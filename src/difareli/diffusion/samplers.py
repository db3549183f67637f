"""Deterministic samplers over one denoiser interface, both directions (SPEC 5, 10).

Every sampler is ``fn(denoiser, x, timesteps, schedule, *, clip_x0=False, callback=None, progress=False,
**opts) -> x`` with ``denoiser(x, t_long[B]) -> eps``. ``timesteps`` is a grid from
``DiffusionSchedule.time_grid`` (or any strictly monotone integer sequence in ``[-1, T]``): descending
generates, ascending inverts, with the same code. Each step goes from ``timesteps[i]`` to ``timesteps[i+1]``
and evaluates the network once, at the current point ``timesteps[i]``.

- ``ddim``: deterministic DDIM (eta 0), SPEC 5 Eq. 4: ``x' = alpha' x0_hat + sigma' eps_hat``.
- ``dpm_solver``: DPM-Solver-2M, noise prediction (Lu et al. 2022, multistep "midpoint" form).
- ``dpm_solver_pp``: DPM-Solver++(2M), data prediction (Lu et al. 2022b).
- ``unipc``: UniPC (Zhao et al. 2023), UniP-2 predictor + UniC corrector, data prediction, B(h) ``bh1|bh2``.

Conventions shared by all (and matching diffusers' schedulers, which the parity tests check):

- Every first-order step is written as the DDIM step ``alpha' x0_hat + sigma' eps_hat``, which is
  DPM-Solver-1, DPM-Solver++-1 and the UniPC base update at once, and stays finite at the grid ends
  (``sigma = 0`` at the clean end ``t = -1``, ``alpha = 0`` at ``t = T``), where ``lambda`` is infinite.
- Multistep solvers take a first-order first step (no history), and drop to first order for any step with
  an infinite ``lambda`` (from/to the clean end or to ``abar = 0``, where the step size ``h`` is infinite and
  the difference quotient undefined) or whose previous point had one. ``lower_order_final`` (default True)
  reproduces diffusers: DPM-Solver(++) makes the last step first order when ``n < 15``; UniPC always does.
- At the clean end of an inversion (``t = -1``) the network is called with ``t = 0``, the nearest level it
  was trained on; ``x0_hat = x`` there exactly, and ``eps_hat`` only enters through ``sigma'`` of the first step.
- ``clip_x0`` (True -> [-1, 1], or a float c -> [-c, c]) clamps ``x0_hat`` and re-derives ``eps_hat`` from it
  (as guided-diffusion's DDIM and the public DiFaReli code do, in both directions).
- Arithmetic runs in float32 (float64 if ``x`` is float64), coefficients in float64; the denoiser runs under
  whatever autocast is active and its output is cast back.
- ``callback(step, t_cur, t_next, x)`` runs after each step; a returned tensor replaces ``x`` (per-step
  mean-matching offsets). UniPC carries that change through its corrector, which rebuilds ``x`` from the
  previous sample and would otherwise discard it.
"""

from __future__ import annotations

import math
from typing import Callable, Literal

import torch
from tqdm.auto import tqdm

from difareli.diffusion.schedule import CLEAN, DiffusionSchedule
from difareli.errors import UserError

Denoiser = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
Callback = Callable[[int, int, int, torch.Tensor], "torch.Tensor | None"]


# ---------------------------------------------------------------------- shared machinery
def _prepare(x: torch.Tensor, timesteps, schedule: DiffusionSchedule):
    """Validate the grid; return it as ints, x in the working dtype and (alpha, sigma, lambda) per point."""
    ts = [int(t) for t in (timesteps.tolist() if hasattr(timesteps, "tolist") else timesteps)]
    if len(ts) < 2:
        raise UserError("a grid needs at least 2 points (1 step)")
    d = [b - a for a, b in zip(ts, ts[1:])]
    if not (all(v > 0 for v in d) or all(v < 0 for v in d)):
        raise UserError(f"grid must be strictly monotone (first points {ts[:8]})")
    if CLEAN in ts[1:-1] or schedule.T in ts[:-1] or (ts[-1] == schedule.T and d[0] < 0):
        raise UserError("t=-1 (clean) may only be a grid end; t=T (abar=0) only the end of an inversion")
    wd = torch.float64 if x.dtype == torch.float64 else torch.float32
    return ts, x.to(wd), [schedule.marginal(t) for t in ts]


class _Model:
    """Calls the denoiser at a grid point and returns consistent ``(x0_hat, eps_hat)``."""

    def __init__(self, denoiser: Denoiser, T: int, clip_x0):
        self.denoiser, self.T = denoiser, T
        self.clip = None if clip_x0 is False or clip_x0 is None else 1.0 if clip_x0 is True else float(clip_x0)

    def __call__(self, x: torch.Tensor, t: int, alpha: float, sigma: float):
        tt = torch.full((x.shape[0],), min(max(t, 0), self.T - 1), dtype=torch.long, device=x.device)
        eps = self.denoiser(x, tt).to(x.dtype)
        x0 = x if sigma == 0.0 else (x - sigma * eps) / alpha
        if self.clip is not None:
            x0 = x0.clamp(-self.clip, self.clip)
            if sigma > 0.0:
                eps = (x - alpha * x0) / sigma
        return x0, eps


def _after(callback, i: int, t: int, tn: int, x: torch.Tensor) -> torch.Tensor:
    if callback is None:
        return x
    out = callback(i, t, tn, x)
    return x if out is None else out.to(x.dtype)


def _steps(n: int, progress: bool, name: str):
    return tqdm(range(n), desc=name, disable=not progress, leave=False)


def _finite(*lams: float) -> bool:
    return all(math.isfinite(v) for v in lams)


# ---------------------------------------------------------------------- samplers
def ddim(denoiser: Denoiser, x: torch.Tensor, timesteps, schedule: DiffusionSchedule, *, clip_x0=False,
         callback: Callback | None = None, progress: bool = False) -> torch.Tensor:
    """Deterministic DDIM (eta 0); on an ascending grid this is DDIM inversion (SPEC 5 Eq. 4)."""
    ts, x, m = _prepare(x, timesteps, schedule)
    model = _Model(denoiser, schedule.T, clip_x0)
    for i in _steps(len(ts) - 1, progress, "ddim"):
        x0, eps = model(x, ts[i], m[i][0], m[i][1])
        x = _after(callback, i, ts[i], ts[i + 1], m[i + 1][0] * x0 + m[i + 1][1] * eps)
    return x


def _dpm_multistep(denoiser, x, timesteps, schedule, *, data_pred: bool, order: int, clip_x0, callback,
                   progress, lower_order_final: bool, name: str) -> torch.Tensor:
    if order not in (1, 2):
        raise UserError(f"order must be 1 or 2, got {order}")
    ts, x, m = _prepare(x, timesteps, schedule)
    model = _Model(denoiser, schedule.T, clip_x0)
    n = len(ts) - 1
    prev = None  # (lambda, model output) at the previous point
    for i in _steps(n, progress, name):
        (a, s, lam), (an, sn, lan) = m[i], m[i + 1]
        x0, eps = model(x, ts[i], a, s)
        out = x0 if data_pred else eps
        x_new = an * x0 + sn * eps
        second = (order == 2 and prev is not None and _finite(prev[0], lam, lan)
                  and not (lower_order_final and n < 15 and i == n - 1))
        if second:
            h = lan - lam
            r0 = (lam - prev[0]) / h
            # D1 = (m0 - m1) / r0; the 2M "midpoint" term is -0.5 alpha'(e^-h - 1) D1 (data prediction)
            # or -0.5 sigma'(e^h - 1) D1 (noise prediction).
            c = -0.5 * (an * math.expm1(-h) if data_pred else sn * math.expm1(h)) / r0
            x_new = x_new + c * (out - prev[1])
        prev = (lam, out)
        x = _after(callback, i, ts[i], ts[i + 1], x_new)
    return x


def dpm_solver(denoiser: Denoiser, x: torch.Tensor, timesteps, schedule: DiffusionSchedule, *, clip_x0=False,
               callback: Callback | None = None, progress: bool = False, order: Literal[1, 2] = 2,
               lower_order_final: bool = True) -> torch.Tensor:
    """DPM-Solver multistep (noise prediction), order 2 by default."""
    return _dpm_multistep(denoiser, x, timesteps, schedule, data_pred=False, order=order, clip_x0=clip_x0,
                          callback=callback, progress=progress, lower_order_final=lower_order_final,
                          name="dpm_solver")


def dpm_solver_pp(denoiser: Denoiser, x: torch.Tensor, timesteps, schedule: DiffusionSchedule, *,
                  clip_x0=False, callback: Callback | None = None, progress: bool = False,
                  order: Literal[1, 2] = 2, lower_order_final: bool = True) -> torch.Tensor:
    """DPM-Solver++ multistep (data prediction), order 2 by default."""
    return _dpm_multistep(denoiser, x, timesteps, schedule, data_pred=True, order=order, clip_x0=clip_x0,
                          callback=callback, progress=progress, lower_order_final=lower_order_final,
                          name="dpm_solver_pp")


def _unipc_coeffs(h: float, variant: str) -> tuple[float, float, float]:
    """``(B(h), b1, b2)`` of UniPC with data prediction (``hh = -h``), in float64 (the phi recursions cancel
    catastrophically in float32 for small h).

    ``b_k = k! h phi_{k+1}(hh) / B(h)`` are the right-hand sides of the corrector's order conditions
    (diffusers' ``b``); B(h) = hh (bh1) or e^hh - 1 (bh2).
    """
    hh = -h
    hphi1 = math.expm1(hh)
    B = hh if variant == "bh1" else hphi1
    phi2 = hphi1 / hh - 1
    phi3 = phi2 / hh - 0.5
    return B, phi2 / B, 2 * phi3 / B


def unipc(denoiser: Denoiser, x: torch.Tensor, timesteps, schedule: DiffusionSchedule, *, clip_x0=False,
          callback: Callback | None = None, progress: bool = False, order: Literal[1, 2] = 2,
          variant: Literal["bh1", "bh2"] = "bh2", corrector: bool = True,
          lower_order_final: bool = True) -> torch.Tensor:
    """UniPC multistep (UniP-``order`` predictor + UniC corrector), data prediction as in diffusers.

    Inversion: no public implementation has one. UniPC's predictor and corrector are exponential-integrator
    formulas in ``h = lambda' - lambda`` derived from Taylor expansions of the data prediction in lambda,
    which hold for either sign of h; an ascending grid is a decreasing-lambda grid, so the same formulas
    with ``h < 0`` (``hh = -h > 0``) invert, each corrector reusing the network evaluation at the next point
    exactly as in generation. Their orders carry over: UniP-2 + UniC measures order ~3 both ways
    (``tests/diffusion/test_samplers_exactness.py``). Steps from the clean end get no corrector (h is infinite there).
    Caveat measured there: in inversion bh2's B(h) = e^|h| - 1 grows with the step, so on grids with huge
    lambda steps near the data (uniform-in-t, ending at t = 0, n <= 20) bh2 inversion is unstable; the
    default clean-ended grids take those steps with DDIM and stay accurate.
    """
    if order not in (1, 2):
        raise UserError(f"order must be 1 or 2, got {order}")
    if variant not in ("bh1", "bh2"):
        raise UserError(f"variant must be 'bh1' or 'bh2', got {variant!r}")
    ts, x, m = _prepare(x, timesteps, schedule)
    model = _Model(denoiser, schedule.T, clip_x0)
    n = len(ts) - 1
    prev = None  # (lambda, x0_hat) at the previous point
    last = None  # what the corrector at the next point needs from the step that led there
    for i in _steps(n, progress, f"unipc-{variant}"):
        (a, s, lam), (an, sn, lan) = m[i], m[i + 1]
        x0, eps = model(x, ts[i], a, s)
        if last is not None:
            x_c = last["base"] + last["coef"] * (x0 - last["m0"])
            if last["prev"] is not None:
                x_c = x_c + last["coef_prev"] * (last["prev"] - last["m0"])
            # The network was evaluated at the predicted x (as in UniPC); only the sample is corrected.
            # Adding (x - x_pred) keeps whatever the callback added to the predicted sample.
            x = x_c + (x - last["x_pred"])
            eps = (x - a * x0) / s
        k = 2 if (order == 2 and prev is not None and _finite(prev[0], lam, lan)
                  and not (lower_order_final and i == n - 1)) else 1
        base = an * x0 + sn * eps  # = sigma'/sigma x - alpha'(e^-h - 1) x0_hat, finite at the ends
        x_pred = base
        last = None
        if _finite(lam, lan):
            h = lan - lam
            B, b1, b2 = _unipc_coeffs(h, variant)
            if k == 2:
                rk = (prev[0] - lam) / h
                # UniP-2: rho_p = 1/2 on D1 = (m1 - m0) / r1 (diffusers' simplified order-2 predictor).
                x_pred = base - an * B * 0.5 / rk * (prev[1] - x0)
                # UniC-2: solve [[1, 1], [r1, 1]] rho = [b1, b2] (rows r^0, r^1 over nodes (r1, 1)).
                rho0 = (b1 - b2) / (1 - rk)
                rho1 = b1 - rho0
                last = {"coef": -an * B * rho1, "prev": prev[1], "coef_prev": -an * B * rho0 / rk}
            else:
                last = {"coef": -an * B * 0.5, "prev": None}  # UniC-1: rho_c = 1/2
            last.update(base=base, m0=x0, x_pred=x_pred)
            if not corrector:
                last = None
        prev = (lam, x0)
        x = _after(callback, i, ts[i], ts[i + 1], x_pred)
    return x


# ---------------------------------------------------------------------- registry
#: Configure and run these through :class:`difareli.diffusion.spec.SamplerSpec`, which reads each function's
#: keyword-only options (beyond clip_x0 / callback / progress) from its signature.
SAMPLERS: dict[str, Callable[..., torch.Tensor]] = {
    "ddim": ddim,
    "dpm_solver": dpm_solver,
    "dpm_solver_pp": dpm_solver_pp,
    "unipc": unipc,
}
