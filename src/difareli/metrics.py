"""Face-region metrics of SPEC 11: DSSIM, MSE and LPIPS-Alex, one value per image.

Conventions shared by every function here:

- ``pred`` and ``target`` are float NCHW RGB tensors in ``[0, data_range]`` (default ``[0, 1]``).
  Network tensors in ``[-1, 1]`` go through :func:`from_signed` first. MSE is reported in these
  units, so ``[0, 1]`` images give the paper's scale (MSE ~ 0.01).
- ``mask`` is ``[B, H, W]`` or ``[B, 1, H, W]``; it is binarised (``> 0.5``, or ``True``) and marks the
  face region (the ``face_mask`` encoding).
- Both images are composited onto black outside the mask before anything is computed, so pixels
  outside the face can never change a score (an SSIM window or an AlexNet receptive field that
  straddles the face border sees identical zeros in both images). Per-pixel maps are then averaged
  over the mask pixels (and the channels). An image whose mask is empty scores NaN.
- Every function returns shape ``[B]`` (float64 for DSSIM/MSE, float32 for LPIPS).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from difareli.lpips import get_lpips

WIN_SIZE = 11
SIGMA = 1.5
K1, K2 = 0.01, 0.03


def from_signed(x: Tensor) -> Tensor:
    """Map network tensors in [-1, 1] to [0, 1]."""
    return (x + 1) / 2


def _check(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    if pred.shape != target.shape or pred.ndim != 4:
        raise ValueError(f"pred/target must be equal NCHW tensors, got {tuple(pred.shape)}, {tuple(target.shape)}")
    if mask.ndim == 3:
        mask = mask[:, None]
    if mask.ndim != 4 or mask.shape[1] != 1 or mask.shape[0] != pred.shape[0] or mask.shape[-2:] != pred.shape[-2:]:
        raise ValueError(f"mask must be [B,H,W] or [B,1,H,W] matching {tuple(pred.shape)}, got {tuple(mask.shape)}")
    return (mask > 0.5) if mask.dtype != torch.bool else mask


def _masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Mean of a [B,C,H,W] map over mask pixels and channels -> [B] (NaN for an empty mask)."""
    m = mask.to(values.dtype).expand_as(values)
    return (values * m).sum(dim=(1, 2, 3)) / m.sum(dim=(1, 2, 3))


def composite(x: Tensor, mask: Tensor) -> Tensor:
    """Keep ``x`` inside the (boolean) mask, black outside."""
    return torch.where(mask, x, torch.zeros((), dtype=x.dtype, device=x.device))


def gaussian_window(win_size: int = WIN_SIZE, sigma: float = SIGMA, dtype=torch.float64) -> Tensor:
    """Normalised 1-D Gaussian taps (scipy's ``gaussian_filter`` with truncate=3.5 gives the same 11)."""
    r = torch.arange(win_size, dtype=dtype) - (win_size - 1) / 2
    g = torch.exp(-(r**2) / (2 * sigma**2))
    return g / g.sum()


def _symmetric_pad(x: Tensor, p: int) -> Tensor:
    # scipy.ndimage mode='reflect' (edge sample repeated: d c b a | a b c d), which skimage uses;
    # torch's F.pad 'reflect' skips the edge sample, so build it by hand.
    x = torch.cat([x[..., :p, :].flip(-2), x, x[..., -p:, :].flip(-2)], dim=-2)
    return torch.cat([x[..., :p].flip(-1), x, x[..., -p:].flip(-1)], dim=-1)


def _blur(x: Tensor, g: Tensor) -> Tensor:
    """Separable Gaussian filter per channel, same output size (symmetric padding)."""
    c, p = x.shape[1], (g.numel() - 1) // 2
    x = _symmetric_pad(x, p)
    x = F.conv2d(x, g.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return F.conv2d(x, g.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)


def ssim_map(pred: Tensor, target: Tensor, data_range: float = 1.0, win_size: int = WIN_SIZE,
             sigma: float = SIGMA) -> Tensor:
    """Per-pixel, per-channel SSIM map [B,C,H,W] in float64 (Wang et al. 2004, Gaussian window).

    Equals skimage's ``structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, full=True)`` map everywhere, borders included (same symmetric
    padding). skimage's scalar SSIM additionally crops ``(win_size - 1) // 2`` pixels per border
    before averaging; pass a mask without that border to reproduce it.
    """
    if min(pred.shape[-2:]) < win_size:
        raise ValueError(f"images must be at least {win_size}x{win_size}")
    x, y = pred.to(torch.float64), target.to(torch.float64)
    g = gaussian_window(win_size, sigma).to(x.device)
    mx, my = _blur(x, g), _blur(y, g)
    vx = _blur(x * x, g) - mx * mx
    vy = _blur(y * y, g) - my * my
    vxy = _blur(x * y, g) - mx * my
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    return ((2 * mx * my + c1) * (2 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))


def dssim(pred: Tensor, target: Tensor, mask: Tensor, data_range: float = 1.0) -> Tensor:
    """DSSIM = (1 - SSIM) / 2 with the SSIM map averaged over mask pixels and channels -> [B]."""
    m = _check(pred, target, mask)
    s = ssim_map(composite(pred, m), composite(target, m), data_range)
    return (1 - _masked_mean(s, m)) / 2


def masked_mse(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Mean squared error over mask pixels and the 3 channels -> [B] (float64)."""
    m = _check(pred, target, mask)
    d = pred.to(torch.float64) - target.to(torch.float64)
    return _masked_mean(d * d, m)


def lpips(pred: Tensor, target: Tensor, mask: Tensor, data_range: float = 1.0) -> Tensor:
    """LPIPS-Alex (v0.1) spatial map averaged over the mask -> [B].

    Both images are composited onto black outside the mask, mapped to [-1, 1], and fed to
    :class:`difareli.lpips.LPIPS` with ``spatial=True``: each layer's 1x1-conv output is bilinearly
    upsampled to the input size and summed (the reference's ``spatial=True`` map); that map is
    averaged over the mask pixels. On a full mask this is the spatial map's mean, which differs
    slightly (bilinear resampling; ~1e-5 here) from the reference's non-spatial scalar.
    """
    m = _check(pred, target, mask)
    net = get_lpips("alex", str(pred.device))
    scale = 2.0 / data_range
    x = composite(pred, m).float() * scale - 1
    y = composite(target, m).float() * scale - 1
    with torch.no_grad():
        d = net(x, y, spatial=True)
    return _masked_mean(d, m)


def evaluate(pred: Tensor, target: Tensor, mask: Tensor, data_range: float = 1.0) -> dict[str, Tensor]:
    """All three SPEC 11 metrics -> ``{"dssim", "mse", "lpips"}``, each [B] on CPU (float64).

    MSE is in the input's units (``[0, 1]`` images: the paper's scale).
    """
    out = {
        "dssim": dssim(pred, target, mask, data_range),
        "mse": masked_mse(pred, target, mask),
        "lpips": lpips(pred, target, mask, data_range),
    }
    return {k: v.detach().to("cpu", torch.float64) for k, v in out.items()}



def binary_scores(pred, target) -> dict[str, "np.ndarray"]:
    """IoU, precision and recall of boolean masks ``(N, ...)`` -> each ``(N,)`` (numpy). NaN where undefined:
    IoU when both are empty, precision when ``pred`` is empty, recall when ``target`` is empty."""
    import numpy as np

    a = np.asarray(pred, bool).reshape(len(pred), -1)
    b = np.asarray(target, bool).reshape(len(target), -1)
    inter = (a & b).sum(1).astype(np.float64)

    def ratio(den):
        return np.where(den > 0, inter / np.maximum(den, 1), np.nan)

    return {"iou": ratio((a | b).sum(1)), "precision": ratio(a.sum(1)), "recall": ratio(b.sum(1))}
