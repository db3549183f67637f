"""DiffusionSchedule: float64 tables, q_sample, and the integer grids samplers walk."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difareli.diffusion import CLEAN, DiffusionSchedule

SCHED = DiffusionSchedule()
T = SCHED.T


def test_tables():
    betas = np.linspace(1e-4, 0.02, 1000)
    np.testing.assert_allclose(SCHED.alphas_cumprod, np.cumprod(1 - betas), rtol=1e-12)
    # 1 - abar is accurate where it is tiny (t = 0: exactly beta_0), which sigma and lambda depend on.
    assert SCHED.one_minus_ac[0] == pytest.approx(1e-4, rel=1e-12)
    np.testing.assert_allclose(SCHED.sqrt_ac**2 + SCHED.sqrt_1m_ac**2, 1.0, rtol=1e-14)
    assert SCHED.alphas_cumprod.dtype == np.float64
    assert SCHED.lambdas[0] == pytest.approx(0.5 * math.log((1 - 1e-4) / 1e-4), rel=1e-12)
    assert SCHED.lambdas[-1] == pytest.approx(-5.0588, abs=1e-4)
    assert np.all(np.diff(SCHED.lambdas) < 0)
    np.testing.assert_allclose(SCHED.log_snr, 2 * SCHED.lambdas)


def test_tables_match_diffusers():
    diffusers = pytest.importorskip("diffusers")
    ref = diffusers.DDPMScheduler(beta_schedule="linear").alphas_cumprod.double().numpy()
    np.testing.assert_allclose(SCHED.alphas_cumprod, ref, rtol=2e-5)  # theirs is float32


def test_marginal_and_sentinels():
    assert SCHED.marginal(CLEAN) == (1.0, 0.0, math.inf)
    assert SCHED.marginal(T) == (0.0, 1.0, -math.inf)
    a, s, lam = SCHED.marginal(500)
    assert a == pytest.approx(math.sqrt(SCHED.alphas_cumprod[500])) and lam == pytest.approx(math.log(a / s))
    assert SCHED.alpha_bar(CLEAN) == 1.0 and SCHED.alpha_bar(T) == 0.0
    for bad in (-2, T + 1):
        with pytest.raises(ValueError):
            SCHED.marginal(bad)


def test_cosine_kind():
    cos = DiffusionSchedule(kind="cosine")
    assert np.all(np.diff(cos.alphas_cumprod) < 0) and cos.betas.max() <= 0.999
    assert cos.alphas_cumprod[499] == pytest.approx(math.cos((0.5 + 0.008) / 1.008 * math.pi / 2) ** 2
                                                    / math.cos(0.008 / 1.008 * math.pi / 2) ** 2, rel=1e-9)
    with pytest.raises(ValueError):
        DiffusionSchedule(kind="sigmoid")


def test_q_sample():
    x0 = torch.linspace(-1, 1, 2 * 3 * 4 * 4).view(2, 3, 4, 4).to(torch.bfloat16)
    noise = torch.randn(2, 3, 4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    t = torch.tensor([0, 999])
    xt = SCHED.q_sample(x0, t, noise)
    assert xt.dtype == torch.float32 and xt.shape == x0.shape
    for b, tb in enumerate(t.tolist()):
        exp = math.sqrt(SCHED.alphas_cumprod[tb]) * x0[b].double() + math.sqrt(SCHED.one_minus_ac[tb]) * noise[b]
        torch.testing.assert_close(xt[b].double(), exp, rtol=1e-6, atol=1e-6)
    ab = SCHED.alphas_cumprod_t(t, xt)
    assert ab.shape == (2, 1, 1, 1) and ab.dtype == torch.float32
    assert float(ab[1]) == pytest.approx(SCHED.alphas_cumprod[999], rel=1e-6)


def test_uniform_grid_values():
    assert SCHED.time_grid(10).tolist() == [999, 899, 799, 699, 599, 499, 399, 299, 199, 99, -1]
    assert SCHED.time_grid(1).tolist() == [999, -1]
    assert SCHED.time_grid(1000).tolist() == list(range(999, -2, -1))
    assert SCHED.time_grid(3, direction="invert").tolist() == [-1, 332, 666, 999]
    # diffusers' "trailing" spacing (DDIM): t_k = round(T - k T/n) - 1, plus the clean end.
    for n in (5, 7, 10, 50, 250):
        trailing = np.round(np.arange(T, 0, -T / n)).astype(int) - 1
        assert SCHED.time_grid(n).tolist() == trailing.tolist() + [-1]


def test_quadratic_and_logsnr_values():
    assert SCHED.time_grid(10, "quadratic").tolist() == [999, 809, 639, 489, 359, 249, 159, 89, 39, 9, -1]
    g = SCHED.time_grid(10, "logsnr").tolist()
    assert g[0] == 999 and g[-2:] == [0, -1]
    lam = SCHED.lambdas[g[:-1]]
    # Uniform in lambda up to integer rounding (steep near t = 0).
    np.testing.assert_allclose(np.diff(lam), (SCHED.lambdas[0] - SCHED.lambdas[-1]) / 9, rtol=0.12)


def test_t0_end_is_diffusers_linspace():
    for n in (5, 10, 50):
        g = SCHED.time_grid(n, end="t0")
        assert g.tolist() == np.linspace(0, 999, n + 1).round()[::-1].astype(int).tolist()
    assert SCHED.time_grid(999, end="t0").tolist() == list(range(999, -1, -1))
    with pytest.raises(ValueError):
        SCHED.time_grid(1000, end="t0")


@pytest.mark.parametrize("kind", ["uniform", "quadratic", "logsnr"])
@pytest.mark.parametrize("end", ["clean", "t0"])
def test_every_n_gives_a_valid_grid(kind, end):
    lo = -1 if end == "clean" else 0
    for n in range(1, T - lo):
        g = SCHED.time_grid(n, kind, end=end).numpy()
        assert len(g) == n + 1 and g[0] == T - 1 and g[-1] == lo and np.all(np.diff(g) < 0), n
        inv = SCHED.time_grid(n, kind, "invert", end=end).numpy()
        assert np.array_equal(inv, g[::-1])


def test_alpha_zero_end_and_errors():
    g = SCHED.time_grid(4, direction="invert", alpha_zero_end=True).tolist()
    assert g == [-1, 249, 499, 749, T]
    for kwargs in ({"n": 0}, {"n": T + 1}, {"n": 5, "kind": "karras"}, {"n": 5, "direction": "up"},
                   {"n": 5, "alpha_zero_end": True}, {"n": 5, "end": "zero"}):
        with pytest.raises(ValueError):
            SCHED.time_grid(**kwargs)
