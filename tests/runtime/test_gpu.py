"""bf16, compile and CUDA-graph relights on CUDA against fp32 eager (skipped without CUDA).

Same relight as ``tests/runtime/test_runtime.py`` (random tiny network, 10-step DDIM invert + self-decode + a batched
decode of two targets at 32 px), same relative L2 error measure. Tolerances: bf16 as on CPU (BF16_TOL);
compile 1e-3 (inductor may pick other float32 kernels than eager, and cuDNN convolutions may use TF32 in either);
CUDA graphs replay the eager kernels: 1e-5.
"""

from __future__ import annotations

import pytest
import torch

from difareli.diffusion.relight import SamplerSpec
from difareli.runtime.core import _GRAPHS, Runtime, clear_caches

from .test_runtime import BF16_TOL, rel_error, random_network, relight_inputs, relight_with

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]
GPU_COMPILE_TOL = 1e-3
GRAPHS_TOL = 1e-5


@pytest.fixture(scope="module")
def case():
    net = random_network("cuda")
    x0, src, tgt = relight_inputs(net, "cuda")
    return net, x0, src, tgt, relight_with(Runtime(device="cuda"), net, x0, src, tgt)


def test_bf16_relight_agrees_with_fp32(case):
    net, x0, src, tgt, ref = case
    out = relight_with(Runtime(device="cuda", precision="bf16"), net, x0, src, tgt)
    assert out.dtype == torch.float32 and 1e-4 < rel_error(out, ref) < BF16_TOL


def test_fp16_relight_agrees_with_fp32(case):
    net, x0, src, tgt, ref = case
    out = relight_with(Runtime(device="cuda", precision="fp16"), net, x0, src, tgt)
    assert torch.isfinite(out).all() and rel_error(out, ref) < BF16_TOL


def test_compiled_relight_agrees_with_eager(case):
    net, x0, src, tgt, ref = case
    out = relight_with(Runtime(device="cuda", compile=True), net, x0, src, tgt)
    assert rel_error(out, ref) < GPU_COMPILE_TOL


def test_cuda_graph_relight_agrees_with_eager_one_graph_per_batch_size(case):
    net, x0, src, tgt, ref = case
    clear_caches(net)
    rt = Runtime(device="cuda", cuda_graphs=True)
    out = relight_with(rt, net, x0, src, tgt)
    assert rel_error(out, ref) < GRAPHS_TOL
    assert len(_GRAPHS[net]) == 2  # batch 1 (invert, self-decode) and batch 2 (decode)
    # New conditions of the same structure reuse the graphs: their tensors are copied into the static buffers.
    x1, src1, tgt1 = relight_inputs(net, "cuda", seed=7)
    out1 = relight_with(rt, net, x1, src1, tgt1)
    assert len(_GRAPHS[net]) == 2
    assert rel_error(out1, relight_with(Runtime(device="cuda"), net, x1, src1, tgt1)) < GRAPHS_TOL
    assert rel_error(out1, out) > 1e-2  # really another condition, not the first one replayed


def test_cuda_graphs_with_a_multistep_sampler_and_interleaved_denoisers(case):
    """UniPC keeps earlier eps (the graph's output must be copied out), and two denoisers of one graph used in
    turn must each see their own condition."""
    net, x0, src, tgt, _ = case
    spec = SamplerSpec(name="unipc", steps=8, options=(("order", 2),))
    rt, eager = Runtime(device="cuda", cuda_graphs=True, precision="bf16"), Runtime(device="cuda", precision="bf16")
    a = relight_with(rt, net, x0, src, tgt, spec)
    assert rel_error(a, relight_with(eager, net, x0, src, tgt, spec)) < GRAPHS_TOL
    c1, c2 = net.condition(*src), net.condition(*relight_inputs(net, "cuda", seed=3)[1])
    d1, d2 = rt.denoiser(net, c1), rt.denoiser(net, c2)
    t = torch.tensor([400], device="cuda")
    with torch.no_grad():
        e2, e1 = d2(x0, t), d1(x0, t)
        assert torch.allclose(e1, eager.denoiser(net, c1)(x0, t), atol=1e-6)
        assert torch.allclose(e2, eager.denoiser(net, c2)(x0, t), atol=1e-6)
