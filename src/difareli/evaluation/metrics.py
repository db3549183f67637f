"""Face-region metrics of SPEC 11: DSSIM, MSE and LPIPS-Alex, per image, under a named *rule*.

Conventions shared by every function here:

- ``pred`` and ``target`` are float NCHW RGB tensors in ``[0, data_range]`` (default ``[0, 1]``).
  Network tensors in ``[-1, 1]`` go through :func:`from_signed` first. MSE is reported in these
  units, so ``[0, 1]`` images give the paper's scale (MSE ~ 0.01).
- ``mask`` is ``[B, H, W]`` or ``[B, 1, H, W]``; it is binarised (``> 0.5``, or ``True``) and marks the
  face region (the ``face_mask`` encoding). An image whose mask is empty scores NaN.
- Every function returns shape ``[B]`` (float64 for DSSIM/MSE, float32 for LPIPS).

The two rules (:data:`RULES`, config key ``metrics.rule``):

- ``paper`` (the default): the authors' evaluator (XezXey/guided-diffusion ``evaluations/evaluator.py``). The SSIM
  map of the *full* images comes from torchmetrics' ``StructuralSimilarityIndexMeasure(data_range=1.0,
  return_full_image=True)`` (11x11 Gaussian window, sigma 1.5, reflect padding) and is averaged over the mask
  pixels and channels, DSSIM = (1 - SSIM) / 2; LPIPS-Alex runs on the full images with ``spatial=True`` and its
  map is averaged over the mask; MSE = sum(((pred - gt) * mask)^2) / sum(mask) over the 3 channels. Pixels outside
  the face reach DSSIM and LPIPS through windows and receptive fields that straddle the face border.
- ``composite``: both images are composited onto black outside the mask first, then the same maps and masked
  means, so pixels outside the face can never change a score (this project's rule before the paper rule became the
  default).

MSE is the same under both rules. :class:`MaskedDSSIM`, :class:`MaskedMSE` and :class:`MaskedLPIPS` are
torchmetrics ``Metric`` s over these per-image scores with summed states, so they reduce correctly under DDP.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor
from torchmetrics import Metric, MetricCollection
from torchmetrics.functional.image import structural_similarity_index_measure

from difareli.errors import UserError
from difareli.nn.lpips import get_lpips

#: The scoring rules; ``paper`` is the default everywhere (``metrics.rule`` in the configs).
RULES = ("paper", "composite")
DEFAULT_RULE = "paper"
RULE_NOTES = {
    "paper": "the authors' evaluator: SSIM (torchmetrics) and LPIPS maps of the full images, averaged over the "
             "face mask; MSE over mask pixels and channels",
    "composite": "both images composited onto black outside the face mask before SSIM and LPIPS; MSE over mask "
                 "pixels and channels",
}
WIN_SIZE = 11
SIGMA = 1.5


def check_rule(rule: str | None) -> str:
    """``rule`` (None: :data:`DEFAULT_RULE`) if it is one of :data:`RULES`, else a ValueError naming them."""
    rule = DEFAULT_RULE if rule is None else rule
    if rule not in RULES:
        raise UserError(f"metrics rule {rule!r} is not one of {', '.join(RULES)} (metrics.rule=paper|composite)")
    return rule


def describe(rule: str | None) -> str:
    """One line stating a rule, for tables, CSVs and model cards: ``rule: paper (...)``."""
    rule = check_rule(rule)
    return f"rule: {rule} ({RULE_NOTES[rule]})"


def unit_tensor(images) -> Tensor:
    """uint8 images (H, W, 3) or (N, H, W, 3) -> float64 [N, 3, H, W] in [0, 1]: what every metric here reads."""
    a = np.asarray(images, dtype=np.float64) / 255.0
    return torch.from_numpy(a[None] if a.ndim == 3 else a).permute(0, 3, 1, 2)


def from_signed(x: Tensor) -> Tensor:
    """Map network tensors in [-1, 1] to [0, 1]."""
    return (x + 1) / 2


def _check(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    if pred.shape != target.shape or pred.ndim != 4:
        raise UserError(f"pred/target must be equal NCHW tensors, got {tuple(pred.shape)}, {tuple(target.shape)}")
    if mask.ndim == 3:
        mask = mask[:, None]
    if mask.ndim != 4 or mask.shape[1] != 1 or mask.shape[0] != pred.shape[0] or mask.shape[-2:] != pred.shape[-2:]:
        raise UserError(f"mask must be [B,H,W] or [B,1,H,W] matching {tuple(pred.shape)}, got {tuple(mask.shape)}")
    return (mask > 0.5) if mask.dtype != torch.bool else mask


def _masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Mean of a [B,C,H,W] map over mask pixels and channels -> [B] (NaN for an empty mask)."""
    m = mask.to(values.dtype).expand_as(values)
    return (values * m).sum(dim=(1, 2, 3)) / m.sum(dim=(1, 2, 3))


def composite(x: Tensor, mask: Tensor) -> Tensor:
    """Keep ``x`` inside the (boolean) mask, black outside."""
    return torch.where(mask, x, torch.zeros((), dtype=x.dtype, device=x.device))


def _inputs(pred: Tensor, target: Tensor, m: Tensor, rule: str) -> tuple[Tensor, Tensor]:
    """The images SSIM and LPIPS see under ``rule``: the full images (paper) or composited ones."""
    return (pred, target) if check_rule(rule) == "paper" else (composite(pred, m), composite(target, m))


def ssim_map(pred: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """Per-pixel, per-channel SSIM map [B,C,H,W] in float64: torchmetrics' ``return_full_image`` map
    (Gaussian 11x11 window, sigma 1.5, K1 = 0.01, K2 = 0.03, reflect padding of 5 pixels)."""
    if min(pred.shape[-2:]) < WIN_SIZE:
        raise UserError(f"images must be at least {WIN_SIZE}x{WIN_SIZE}")
    _, full = structural_similarity_index_measure(pred.to(torch.float64), target.to(torch.float64),
                                                  gaussian_kernel=True, sigma=SIGMA, kernel_size=WIN_SIZE,
                                                  data_range=float(data_range), reduction="none",
                                                  return_full_image=True)
    return full


def dssim(pred: Tensor, target: Tensor, mask: Tensor, data_range: float = 1.0, rule: str | None = None) -> Tensor:
    """DSSIM = (1 - SSIM) / 2 with the SSIM map averaged over mask pixels and channels -> [B]."""
    m = _check(pred, target, mask)
    s = ssim_map(*_inputs(pred, target, m, check_rule(rule)), data_range)
    return (1 - _masked_mean(s, m)) / 2


def masked_mse(pred: Tensor, target: Tensor, mask: Tensor, rule: str | None = None) -> Tensor:
    """Mean squared error over mask pixels and the 3 channels -> [B] (float64); the same under every rule."""
    check_rule(rule)
    m = _check(pred, target, mask)
    d = pred.to(torch.float64) - target.to(torch.float64)
    return _masked_mean(d * d, m)


def image_errors(image, target, mask=None) -> dict[str, float]:
    """MSE and DSSIM of a uint8 image against another (H, W, 3) on a mask (None: the whole image), rounded for
    people to read: the app's reconstruction error (a source relit under its own light, against itself)."""
    m = torch.from_numpy(np.ones(np.shape(image)[:2], bool) if mask is None else np.array(mask, bool))[None]
    pred, want = unit_tensor(image), unit_tensor(target)
    return {"mse": round(float(masked_mse(pred, want, m)[0]), 5), "dssim": round(float(dssim(pred, want, m)[0]), 5)}


def lpips(pred: Tensor, target: Tensor, mask: Tensor, data_range: float = 1.0, rule: str | None = None) -> Tensor:
    """LPIPS-Alex (v0.1) spatial map averaged over the mask -> [B].

    The images (full, or composited under ``rule=composite``) are mapped to [-1, 1] and fed to
    :class:`difareli.nn.lpips.LPIPS` with ``spatial=True``: each layer's 1x1-conv output is bilinearly upsampled to
    the input size and summed (the reference's ``spatial=True`` map); that map is averaged over the mask pixels.
    On a full mask this is the spatial map's mean, which differs slightly (bilinear resampling; ~1e-5 here) from
    the reference's non-spatial scalar.
    """
    m = _check(pred, target, mask)
    x, y = _inputs(pred, target, m, check_rule(rule))
    net = get_lpips("alex", str(pred.device))
    scale = 2.0 / data_range
    with torch.no_grad():
        d = net(x.float() * scale - 1, y.float() * scale - 1, spatial=True)
    return _masked_mean(d, m)


def evaluate(pred: Tensor, target: Tensor, mask: Tensor, data_range: float = 1.0,
             rule: str | None = None) -> dict[str, Tensor]:
    """All three SPEC 11 metrics under ``rule`` (None: ``paper``) -> ``{"dssim", "mse", "lpips"}``, each [B] on
    CPU (float64). MSE is in the input's units (``[0, 1]`` images: the paper's scale)."""
    rule = check_rule(rule)
    out = {
        "dssim": dssim(pred, target, mask, data_range, rule),
        "mse": masked_mse(pred, target, mask),
        "lpips": lpips(pred, target, mask, data_range, rule),
    }
    return {k: v.detach().to("cpu", torch.float64) for k, v in out.items()}


# ------------------------------------------------------------------------------------- torchmetrics Metrics
class _MaskedImageMetric(Metric):
    """Mean (and standard error) over images of one per-image masked score.

    States are sums (``total``, ``total_sq``, ``count``; ``dist_reduce_fx="sum"``), so the mean over all
    processes' images is exact under DDP. Non-finite per-image scores (an empty mask) are left out and counted in
    ``skipped``. ``last`` holds the per-image scores of the latest :meth:`update` (not a state: this process's
    batch), for callers that also write per-image rows (the benchmark).
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, rule: str | None = None, data_range: float = 1.0, **kwargs):
        super().__init__(**kwargs)
        self.rule, self.data_range = check_rule(rule), float(data_range)
        for name in ("total", "total_sq"):
            self.add_state(name, torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        for name in ("count", "skipped"):
            self.add_state(name, torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")
        self.last: Tensor | None = None

    def score(self, pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def update(self, pred: Tensor, target: Tensor, mask: Tensor) -> None:
        """Score a batch (``[B,3,H,W]`` images in ``[0, data_range]``, a ``[B,(1,)H,W]`` mask) and add it."""
        v = self.score(pred, target, mask).detach().to(self.total.device, torch.float64)
        self.last = v.cpu()
        ok = torch.isfinite(v)
        self.total += v[ok].sum()
        self.total_sq += (v[ok] ** 2).sum()
        self.count += ok.sum()
        self.skipped += (~ok).sum()

    def compute(self) -> Tensor:
        """The mean over every scored image (NaN before any)."""
        return self.total / self.count if self.count > 0 else torch.tensor(float("nan"), dtype=torch.float64)

    def stat(self) -> tuple[float, float, int]:
        """``(mean, SE, n)`` over every process's images, SE = std(ddof=1) / sqrt(n) (NaN when n < 2)."""
        with self.sync_context():
            n = int(self.count)
            mean = float(self.total / n) if n else float("nan")
            var = (float(self.total_sq) - n * mean * mean) / (n - 1) if n > 1 else float("nan")
            return mean, (max(var, 0.0) / n) ** 0.5 if n > 1 else float("nan"), n


class MaskedDSSIM(_MaskedImageMetric):
    """Mean DSSIM on the face mask under ``rule`` (:func:`dssim`)."""

    def score(self, pred, target, mask):
        return dssim(pred, target, mask, self.data_range, self.rule)


class MaskedMSE(_MaskedImageMetric):
    """Mean MSE on the face mask (:func:`masked_mse`)."""

    def score(self, pred, target, mask):
        return masked_mse(pred, target, mask)


class MaskedLPIPS(_MaskedImageMetric):
    """Mean LPIPS-Alex on the face mask under ``rule`` (:func:`lpips`)."""

    def score(self, pred, target, mask):
        return lpips(pred, target, mask, self.data_range, self.rule)


class FiniteMean(Metric):
    """Mean (and SE) over images of a per-image score computed elsewhere (the identity cosine, the lighting error,
    shadow adherence: :mod:`difareli.evaluation.extras`); NaN scores (undefined for that image) are counted in
    ``skipped``, never averaged. Summed states, so exact under DDP."""

    is_differentiable = False
    full_state_update = False
    stat = _MaskedImageMetric.stat
    compute = _MaskedImageMetric.compute

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        for name in ("total", "total_sq"):
            self.add_state(name, torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        for name in ("count", "skipped"):
            self.add_state(name, torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, values) -> None:
        """Add per-image scores (a number or a sequence of them)."""
        v = torch.as_tensor(values, dtype=torch.float64, device=self.total.device).reshape(-1)
        ok = torch.isfinite(v)
        self.total += v[ok].sum()
        self.total_sq += (v[ok] ** 2).sum()
        self.count += ok.sum()
        self.skipped += (~ok).sum()


def relight_metrics(rule: str | None = None, data_range: float = 1.0, prefix: str | None = None,
                    postfix: str | None = None) -> MetricCollection:
    """The three metrics as one collection ``{dssim, mse, lpips}`` (keys get ``prefix``/``postfix``)."""
    return MetricCollection({"dssim": MaskedDSSIM(rule, data_range), "mse": MaskedMSE(rule, data_range),
                             "lpips": MaskedLPIPS(rule, data_range)}, prefix=prefix, postfix=postfix,
                            compute_groups=False)


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
