"""The runtime's inference copy (difareli.runtime.inference_copy): weights cast once to the autocast dtype and
channels-last give the passes autocast gives on the original network, follow every change of the original's weights,
and never touch the caller's network."""

from __future__ import annotations

import pytest
import torch

from difareli.runtime.inference_copy import inference_copy
from difareli.runtime.core import Runtime, clear_caches
from tests.runtime.test_runtime import BF16_TOL, random_network, rel_error, relight_inputs

pytestmark = pytest.mark.usefixtures("one_thread")


def _eps(rt: Runtime, net, seed: int = 3) -> torch.Tensor:
    x0, source, _ = relight_inputs(net, seed=seed)
    with torch.no_grad():
        cond = net.condition(*source)
        t = torch.tensor([500])
        return rt.denoiser(net, cond)(x0, t)


@torch.no_grad()
def test_precast_weights_give_autocasts_passes_bit_for_bit():
    net = random_network()
    copy = inference_copy(net, torch.bfloat16, channels_last=False)
    convs = [m for m in copy.modules() if isinstance(m, torch.nn.Conv2d)]
    assert convs and all(m.weight.dtype == torch.bfloat16 for m in convs)
    norms = [m for m in copy.modules() if isinstance(m, torch.nn.GroupNorm)]
    assert norms and all(m.weight.dtype == torch.float32 for m in norms)  # autocast leaves norms in float32
    x0, source, _ = relight_inputs(net)
    cond = net.condition(*source)
    t = torch.tensor([300])
    with torch.autocast("cpu", dtype=torch.bfloat16, cache_enabled=False):
        ref = net(x0, t, cond).float()
        out = copy(x0, t, cond).float()
    assert torch.equal(out, ref) and ref.abs().max() > 0.1


@torch.no_grad()
def test_channels_last_bf16_runtime_matches_the_original_and_leaves_it_alone():
    net = random_network()
    before = {k: (v.dtype, v.is_contiguous(), v.clone()) for k, v in net.state_dict().items()}
    rt = Runtime(device="cpu", precision="bf16")
    assert rt.memory_format == "channels_last"  # auto: channels-last for bf16 on a CPU
    eps = _eps(rt, net)
    ref = _eps(Runtime(device="cpu", precision="bf16", memory_format="contiguous"), net)
    # same arithmetic in another layout: only the order of float sums differs (bf16 outputs, ~1e-2 relative)
    assert torch.allclose(eps, ref, rtol=0.05, atol=0.02 * ref.abs().max().item())
    for k, v in net.state_dict().items():
        dtype, contiguous, value = before[k]
        assert v.dtype == dtype and v.is_contiguous() == contiguous and torch.equal(v, value)
    assert Runtime(device="cpu", precision="fp32").memory_format == "contiguous"
    with pytest.raises(ValueError, match="memory_format"):
        Runtime(device="cpu", memory_format="nhwc")


@torch.no_grad()
@pytest.mark.parametrize("change", ["load_state_dict", "in_place", "replace_data"])
def test_copy_follows_every_change_of_the_original(change):
    net, other = random_network(seed=0), random_network(seed=1)
    rt = Runtime(device="cpu", precision="bf16")
    first = _eps(rt, net)
    if change == "load_state_dict":
        net.load_state_dict(other.state_dict())
    elif change == "in_place":
        for p, q in zip(net.parameters(), other.parameters()):
            p.copy_(q)
    else:
        for p, q in zip(net.parameters(), other.parameters()):
            p.data = q.data.clone()
    after = _eps(rt, net)
    clear_caches(other)
    expected = _eps(rt, other)
    assert not torch.equal(after, first)
    assert torch.equal(after, expected)  # the refreshed copy equals a copy made from the new weights


@torch.no_grad()
def test_runtime_condition_runs_the_modulator_on_the_inference_copy():
    """Runtime.condition (a one-pass model's Modulator at every relight): contiguous bf16 equals autocast on the
    original network bit for bit; channels-last gives channels-last states within the runtime's bf16 tolerance
    (relative L2, BF16_TOL) of it, and no further from fp32 than bf16 itself is; fp32 is the plain condition; the
    caller's network is left alone."""
    net = random_network()
    _, source, _ = relight_inputs(net)
    with torch.autocast("cpu", dtype=torch.bfloat16, cache_enabled=False):
        ref = net.condition(*source)
    plain = net.condition(*source)
    flat = Runtime(device="cpu", precision="bf16", memory_format="contiguous").condition(net, *source)
    assert all(torch.equal(a, b) for a, b in zip(flat.spatial, ref.spatial))
    assert torch.equal(flat.nonspatial, ref.nonspatial)
    cl = Runtime(device="cpu", precision="bf16").condition(net, *source)
    for a, b in zip(cl.spatial, ref.spatial):
        assert a.is_contiguous(memory_format=torch.channels_last)
        assert a.dtype == b.dtype == torch.bfloat16 and rel_error(a, b) < BF16_TOL
    for a, b, p in zip(cl.spatial, ref.spatial, plain.spatial):
        assert rel_error(a, p) < 1.5 * rel_error(b, p) + 1e-3
    assert any(not torch.equal(a, b) for a, b in zip(ref.spatial, plain.spatial))  # bf16 did change the states
    fp32 = Runtime(device="cpu", precision="fp32").condition(net, *source)
    assert all(torch.equal(a, b) for a, b in zip(fp32.spatial, plain.spatial))
    assert all(p.dtype == torch.float32 for p in net.parameters())
