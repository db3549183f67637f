"""runtime.compile=true on a machine without a working C++ compiler: one warning saying why and how
to get compile, then the eager result; torch.compile itself is simulated (a real compile takes minutes here)."""

from __future__ import annotations

import pytest
import torch

from difareli.runtime import core as rt


class Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(4, 4)

    def forward(self, x, t, cond):
        return self.lin(x) * cond + t[:, None]


def _no_compiler(forward, **kwargs):
    from torch._inductor.exc import InvalidCxxCompiler

    def call(*args, **kw):  # torch.compile is lazy: inductor fails at the first call
        raise InvalidCxxCompiler()

    return call


def _wrapped_no_compiler(forward, **kwargs):
    from torch._inductor.exc import InvalidCxxCompiler

    def call(*args, **kw):  # dynamo reports a backend failure with the compiler error as its cause
        try:
            raise InvalidCxxCompiler()
        except InvalidCxxCompiler as e:
            raise RuntimeError("backend='inductor' raised: InvalidCxxCompiler") from e

    return call


@pytest.mark.parametrize("fake", [_no_compiler, _wrapped_no_compiler])
def test_compile_without_a_cxx_compiler_falls_back_to_eager_with_one_warning(monkeypatch, fake):
    torch.manual_seed(0)
    net = Net().eval()
    x, t, cond = torch.randn(2, 4), torch.tensor([1.0, 2.0]), torch.tensor(0.5)
    eager = rt.Runtime(device="cpu").denoiser(net, cond)
    monkeypatch.setattr(torch, "compile", fake)
    rt.clear_caches(net)
    try:
        den = rt.Runtime(device="cpu", compile=True).denoiser(net, cond)
        with pytest.warns(UserWarning) as caught:
            out = den(x, t)
        assert len(caught) == 1
        msg = str(caught[0].message)
        assert msg.startswith("runtime.compile=true but torch.compile cannot build kernels here (No working C++ "
                              "compiler found")
        assert "running eagerly" in msg and "install a C++ compiler (e.g. apt-get install g++" in msg
        torch.testing.assert_close(out, eager(x, t), rtol=0, atol=0)
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("error")  # later calls: eager, no second warning, no retried compile
            torch.testing.assert_close(den(x, t), eager(x, t), rtol=0, atol=0)
    finally:
        rt.clear_caches(net)


def test_other_compile_errors_are_not_hidden(monkeypatch):
    def broken(forward, **kwargs):
        def call(*args, **kw):
            raise RuntimeError("a bug in the traced code")

        return call

    net = Net().eval()
    monkeypatch.setattr(torch, "compile", broken)
    rt.clear_caches(net)
    try:
        den = rt.Runtime(device="cpu", compile=True).denoiser(net, torch.tensor(0.5))
        with pytest.raises(RuntimeError, match="a bug in the traced code"):
            den(torch.randn(2, 4), torch.tensor([1.0, 2.0]))
    finally:
        rt.clear_caches(net)
