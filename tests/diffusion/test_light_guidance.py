"""Light guidance of a relight's decode (``sampler.guidance``): eps_s + w (eps_t - eps_s), checked in closed form
on linear denoisers, through a whole decode against a decode whose denoiser is the combined one, and through the
tensor-level relight of a real (untrained) model, where w = 1 is the plain decode bit for bit."""

from __future__ import annotations

import pytest
import torch

from difareli.diffusion.relight import decode, guided, invert
from difareli.diffusion.schedule import DiffusionSchedule
from difareli.diffusion.spec import SamplerConfigError, SamplerSpec
from difareli.errors import UserError


def test_guided_is_the_extrapolation_of_two_denoisers():
    x, t = torch.randn(2, 3, 4, 4), torch.tensor([10, 10])
    src, tgt = (lambda x, t: 0.5 * x), (lambda x, t: -x + 1.0)
    for w in (0.5, 1.0, 2.0, 3.5):
        want = 0.5 * x + w * ((-x + 1.0) - 0.5 * x)
        torch.testing.assert_close(guided(tgt, src, w)(x, t), want)
    assert guided(tgt, src, 1.0) is tgt  # no second pass when it changes nothing


def test_a_guided_decode_is_the_decode_of_the_combined_denoiser():
    sched = DiffusionSchedule()
    x0 = torch.rand(2, 3, 8, 8) * 2 - 1
    src, tgt = (lambda x, t: 0.1 * x), (lambda x, t: 0.1 * x + 0.05)
    spec = SamplerSpec("ddim", steps=6, guidance=2.5)
    inv = invert(src, x0, sched, spec)
    out = decode(tgt, inv, sched, source=src)
    ref = decode(lambda x, t: 0.1 * x + 2.5 * 0.05, invert(src, x0, sched, SamplerSpec("ddim", steps=6)), sched)
    torch.testing.assert_close(out, ref)
    with pytest.raises(UserError, match="guidance=2.5 needs the source's denoiser"):
        decode(tgt, inv, sched)


def test_guidance_is_checked_and_round_trips():
    spec = SamplerSpec.from_config({"preset": "default", "guidance": 2})
    assert spec.guidance == 2.0 and SamplerSpec.from_config(spec.to_config()) == spec
    # At 1 a spec records as before guidance existed: earlier benchmark runs' settings still match.
    assert "guidance" not in SamplerSpec.preset("default").to_config()
    for bad in (0, -1, 11, "strong", True):
        with pytest.raises(SamplerConfigError, match="sampler guidance must be a number in"):
            SamplerSpec("ddim", guidance=bad)


def test_relight_with_guidance_one_is_the_plain_relight_and_more_moves_further():
    from difareli.perf.measure import random_condition, untrained_model
    from difareli.relight.core import relight

    torch.manual_seed(0)
    model, res = untrained_model("difareli_pp", "tiny", 16)
    # A zero-initialised output conv would make every eps 0: give the untrained network a response.
    torch.nn.init.normal_(model.net.unet.out[-1].weight, std=0.05)
    x0 = torch.rand(1, 3, res, res) * 2 - 1
    source = random_condition(model, 1, res, seed=1)
    targets = random_condition(model, 3, res, seed=2)
    plain = relight(model, x0, source, targets, SamplerSpec("ddim", steps=4))
    one = relight(model, x0, source, targets, SamplerSpec("ddim", steps=4, guidance=1.0))
    assert torch.equal(plain, one)
    self_decode = relight(model, x0, source, source, SamplerSpec("ddim", steps=4)).expand(3, -1, -1, -1)
    far = relight(model, x0, source, targets, SamplerSpec("ddim", steps=4, guidance=3.0))
    # Guidance moves each relight further from the image decoded under the source's own condition.
    assert ((far - self_decode).abs().mean() > (plain - self_decode).abs().mean() * 1.5)
