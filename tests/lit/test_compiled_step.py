"""The compiled training step (``model.compile=true``, the CPU reference recipes' default) computes the eager
step's loss and gradients: the same module weights, batch, timesteps and noise, one step each way.

Tolerances: fp32 ``rtol=1e-4`` on the loss and on each gradient's norm-relative error (inductor reorders float32
reductions and fuses elementwise chains: differences of ~1e-6 relative); bf16 autocast ``2e-2`` on the loss and
``5e-2`` norm-relative per gradient (both paths round every convolution's inputs to bf16, but not at the same
points once inductor fuses the casts).
"""

from __future__ import annotations

import copy
import warnings

import pytest
import torch

from difareli.perf.measure import build_model, random_batch
from difareli.runtime import core as rt


def _step(module, batch, bf16: bool):
    g = torch.Generator().manual_seed(7)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        loss = module.diffusion_loss(batch, generator=g)
    loss.backward()
    return loss.detach().float(), {n: p.grad.detach().clone() for n, p in module.net.named_parameters()
                                   if p.grad is not None}


@pytest.mark.slow
@pytest.mark.parametrize("bf16", [False, True], ids=["fp32", "bf16-mixed"])
def test_compiled_step_equals_eager(bf16):
    if bf16 and not torch.backends.mkldnn.is_available():
        pytest.skip("bf16 autocast on a CPU needs oneDNN")
    # tiny with one level fewer and narrower: the same blocks (AdaGN, attention, Modulator), a graph that compiles
    # in a third of the time
    small = {"channel_mult": [1, 2], "base_channels": 16, "norm_groups": 8, "adagn_hidden": 32}
    eager = build_model("difareli_pp", "tiny", 16, seed=0, net_overrides=small).train()
    compiled = copy.deepcopy(eager)
    assert rt.compile_for_training(compiled.net)
    batch = random_batch(eager, 4)
    loss_e, grads_e = _step(eager, batch, bf16)
    loss_c, grads_c = _step(compiled, batch, bf16)
    assert grads_e.keys() == grads_c.keys() and len(grads_e) > 30
    torch.testing.assert_close(loss_c, loss_e, rtol=2e-2 if bf16 else 1e-4, atol=0)
    tol = 5e-2 if bf16 else 1e-4
    worst = max(((grads_c[n] - g).norm() / g.norm().clamp_min(1e-12)).item() for n, g in grads_e.items())
    assert worst < tol
    # The compiled module is the same module: same parameter names, same state.
    assert list(compiled.state_dict()) == list(eager.state_dict())


def test_compile_for_training_without_a_compiler_stays_eager_with_one_warning(monkeypatch):
    from torch._inductor import cpp_builder
    from torch._inductor.exc import InvalidCxxCompiler

    def missing():
        raise InvalidCxxCompiler()

    monkeypatch.setattr(cpp_builder, "get_cpp_compiler", missing)
    net = torch.nn.Linear(3, 3)
    with pytest.warns(UserWarning, match=r"model.compile=true but torch.compile cannot build kernels here") as w:
        assert not rt.compile_for_training(net)
    assert len(w) == 1 and "training eagerly" in str(w[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert net(torch.ones(1, 3)).shape == (1, 3)  # eager, no compile attempted
