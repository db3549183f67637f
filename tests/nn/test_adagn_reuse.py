"""AdaGN's k = MLP3(nonspatial) computed once per prepared condition in inference (nn.reuse.ReusedVector): every
step's eps equal to the pass that recomputes it, each MLP3 run once over a sampler's steps, and recomputed where
reuse would be wrong (autograd, a vector changed in place)."""

from __future__ import annotations

import pytest
import torch

from difareli.nn import reuse
from difareli.nn.unet import MLP3

from .test_nn import inputs, make

pytestmark = pytest.mark.usefixtures("one_thread")


def _counting(net) -> list[int]:
    """How many times the network's MLP3s run (one counter for all)."""
    calls = [0]
    for m in net.modules():
        if isinstance(m, MLP3):
            m.register_forward_hook(lambda *a: calls.__setitem__(0, calls[0] + 1))
    return calls


def _steps(net, cond, x, allowed: bool, monkeypatch) -> list[torch.Tensor]:
    monkeypatch.setattr(reuse, "allowed", lambda: allowed)
    return [net(x, torch.full((x.shape[0],), t), cond) for t in (999, 500, 3)]


@pytest.mark.parametrize("precision", [None, torch.bfloat16])
def test_reused_scales_give_every_step_the_same_eps_bit_for_bit(precision, monkeypatch):
    net = make("difareli++")
    x, spatial, nonspatial = inputs("difareli++")
    with torch.no_grad(), torch.autocast("cpu", dtype=precision or torch.float32, enabled=precision is not None):
        cond = net.condition(spatial, nonspatial)
        again = _steps(net, cond, x, False, monkeypatch)
        reused = _steps(net, cond, x, True, monkeypatch)
    for a, b in zip(again, reused):
        assert torch.equal(a, b)


def test_each_mlp3_runs_once_over_the_steps_of_one_condition(monkeypatch):
    net = make("difareli++")
    calls = _counting(net)
    mlps = sum(isinstance(m, MLP3) for m in net.modules())
    x, spatial, nonspatial = inputs("difareli++")
    with torch.no_grad():
        cond = net.condition(spatial, nonspatial)
        _steps(net, cond, x, True, monkeypatch)
        assert calls[0] == mlps  # three steps, one run each
        _steps(net, net.condition(spatial, nonspatial), x, True, monkeypatch)
        assert calls[0] == 2 * mlps  # a new condition computes its own
        _steps(net, cond, x, False, monkeypatch)
        assert calls[0] == 5 * mlps  # no reuse: every step runs them


def test_a_vector_changed_in_place_is_computed_again(monkeypatch):
    net = make("difareli++")
    x, spatial, nonspatial = inputs("difareli++")
    monkeypatch.setattr(reuse, "allowed", lambda: True)
    with torch.no_grad():
        cond = net.condition(spatial, nonspatial.clone())  # the condition holds the vector itself
        net(x, torch.full((2,), 10), cond)
        cond.nonspatial.mul_(2.0)
        changed = net(x, torch.full((2,), 10), cond)
        fresh = net(x, torch.full((2,), 10), net.condition(spatial, 2.0 * nonspatial))
    assert torch.equal(changed, fresh)


def test_training_and_crossattention_pass_the_vector_itself():
    with torch.enable_grad():
        assert not reuse.allowed()  # autograd needs the MLP3s in each step's graph
    with torch.no_grad():
        assert reuse.allowed()
    net = make("difareli++", nonspatial={"type": "crossattn"})
    assert not net.nonspatial.reusable  # its blocks take context tokens, not a vector to wrap


@pytest.mark.parametrize("where", ["compiling", "capturing"])
def test_no_reuse_inside_a_compiled_pass_or_a_cuda_graph_capture(where, monkeypatch):
    """A traced or captured pass is replayed with the next condition's values in place: its k must come from
    its own inputs (the stand-ins below say what torch.compile and a CUDA-graph capture report)."""
    if where == "compiling":
        monkeypatch.setattr(torch.compiler, "is_compiling", lambda: True)
    else:
        monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
        monkeypatch.setattr(torch.cuda, "is_current_stream_capturing", lambda: True)
    with torch.no_grad():
        assert not reuse.allowed()
