"""The relit face back in the whole photo: the aligned crop warped through the inverse of the alignment
transform into the original photo at its resolution, blended with a feathered face / hair mask (kornia).

The alignment (:mod:`difareli.estimators.align`) resamples the oriented square ``quad`` of the photo (continuous
pixel coordinates: top-left, bottom-left, bottom-right, top-right) to ``size`` x ``size``; crop pixel index
``(u, v)`` maps to photo pixel index ``M @ (u, v, 1)`` with :func:`~difareli.estimators.align.crop_to_photo`. The
composite works only in the window of the photo that the crop covers, so its cost follows the face, not the photo.

Two transfers (``mode``):

- ``pixels``: the relit crop itself, warped back (bilinear) and blended in: at 64 px the face comes back as
  soft as a 64 px face upsampled;
- ``ratio`` (default): the photo times the relit crop's per-pixel gain over the aligned input,
  ``(W(relit) + eps) / (W(input) + eps)`` clipped to ``[0, max_gain]`` (images are linear, so relighting is a
  change of shading: a gain). The photo's own detail survives at full resolution, and a relight that returns
  its input gives back the photo exactly.

The blend mask is the masks encoding's ``parts`` (face parts, hair, neck, hat) in crop space, blurred by a
Gaussian of ``feather`` x the crop size and faded to zero over the same width at the crop border (so clothes cut
by the crop never leave an edge), then warped like the image. Outside its support the photo is untouched. Where
the crop ran past the photo's edge (``inside``: the crop pixels that sampled the photo) the padding's mask is
its nearest photo pixel's before the blur: the padding (labelled background there) never fades the blend at
the photo's edge, and it lands outside the photo, so nothing made of it comes back.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from difareli.data.encodings import PART_INDEX
from difareli.errors import UserError
from difareli.estimators.align import crop_to_photo, photo_window

#: Parts of the ``masks`` label map blended back by default (the model relights them; the background keeps the
#: photo's own light, since only the crop's share of it was seen).
DEFAULT_PARTS = ("skin", "l_brow", "r_brow", "l_eye", "r_eye", "nose", "u_lip", "l_lip", "mouth", "neck", "hair",
                 "hat")
MODES = ("ratio", "pixels")


def part_mask(labels: np.ndarray, parts: Sequence[str] = DEFAULT_PARTS) -> np.ndarray:
    """Bool (H, W): pixels of the label map ``labels`` (indices into ``MASK_PARTS``) in ``parts``."""
    unknown = [p for p in parts if p not in PART_INDEX]
    if unknown:
        raise UserError(f"unknown mask parts {unknown}; the parts are {list(PART_INDEX)}")
    return np.isin(np.asarray(labels), [PART_INDEX[p] for p in parts])


def feathered(mask: np.ndarray, feather: float) -> torch.Tensor:
    """A crop-space bool mask (S, S) -> float [1, 1, S, S]: Gaussian-blurred by ``feather`` x S and faded to 0
    over that width at the crop border."""
    import kornia

    size = mask.shape[-1]
    m = torch.from_numpy(np.asarray(mask, dtype=np.float32))[None, None]
    sigma = feather * size
    if sigma > 0:
        k = 2 * math.ceil(3 * sigma) + 1
        m = kornia.filters.gaussian_blur2d(m, (k, k), (sigma, sigma), border_type="constant")
    # Border ramp: 0 at the crop's edge pixels, 1 from 3 sigma (at least 2 px) inside.
    width = max(3 * sigma, 2.0)
    d = torch.arange(size, dtype=torch.float32)
    d = torch.minimum(d, size - 1 - d)
    ramp = (d / width).clamp(0, 1)
    return m * ramp[None, None, :, None] * ramp[None, None, None, :]


@dataclass(frozen=True)
class Compositor:
    """Puts relit crops of one photo back into it (module doc): ``compositor(relit)`` -> (N, H, W, 3) uint8."""

    photo: np.ndarray        # (H, W, 3) uint8, the decoded original
    aligned: np.ndarray      # (S, S, 3) uint8, the aligned crop the model read
    labels: np.ndarray       # (S, S) uint8, its masks encoding
    quad: np.ndarray         # (4, 2) float, the alignment quad in photo coordinates
    mode: str = "ratio"
    feather: float = 0.03
    parts: tuple[str, ...] = DEFAULT_PARTS
    eps: float = 4.0 / 255.0
    max_gain: float = 4.0
    chunk: int = 8
    inside: np.ndarray | None = None  # bool (S, S): crop pixels that sampled the photo (None: all)

    def __post_init__(self):
        if self.mode not in MODES:
            raise UserError(f"composite mode must be one of {MODES}, got {self.mode!r}")
        if self.aligned.shape[:2] != self.labels.shape[:2]:
            raise UserError(f"aligned crop {self.aligned.shape} and masks {self.labels.shape} differ in size")

    @property
    def size(self) -> int:
        return int(self.aligned.shape[0])

    def _warp(self, crops: torch.Tensor, window: tuple[int, int, int, int]) -> torch.Tensor:
        """Crops [N, C, S, S] -> the photo window [N, C, h, w] (bilinear, zero outside the crop)."""
        import kornia

        y0, y1, x0, x1 = window
        m = crop_to_photo(self.quad, self.size)
        m[:, 2] -= (x0, y0)
        mt = torch.as_tensor(m, dtype=torch.float32)[None].expand(len(crops), 2, 3)
        return kornia.geometry.transform.warp_affine(crops, mt, (y1 - y0, x1 - x0), mode="bilinear",
                                                     padding_mode="zeros", align_corners=True)

    def _crop_mask(self) -> torch.Tensor:
        """The feathered blend mask in crop space [1, 1, S, S]."""
        m = part_mask(self.labels, self.parts)
        inside = None if self.inside is None else np.asarray(self.inside, bool)
        if inside is not None and inside.any() and not inside.all():
            from scipy import ndimage

            idx = ndimage.distance_transform_edt(~inside, return_distances=False, return_indices=True)
            m = m[idx[0], idx[1]]
        return feathered(m, self.feather)

    def mask(self) -> np.ndarray:
        """The blend mask (H, W) float32 in [0, 1] in photo coordinates."""
        out = np.zeros(self.photo.shape[:2], np.float32)
        window = photo_window(self.quad, self.photo.shape[:2])
        if window is not None:
            y0, y1, x0, x1 = window
            out[y0:y1, x0:x1] = self._warp(self._crop_mask(), window)[0, 0]
        return out

    def __call__(self, relit: np.ndarray) -> np.ndarray:
        """Relit crops (N, S, S, 3) or one (S, S, 3), uint8 -> composites (N, H, W, 3) or (H, W, 3) uint8."""
        relit = np.asarray(relit)
        single = relit.ndim == 3
        relit = relit[None] if single else relit
        if relit.shape[1:] != self.aligned.shape:
            raise UserError(f"relit crops {relit.shape[1:]} differ from the aligned crop {self.aligned.shape}")
        out = np.broadcast_to(self.photo, (len(relit), *self.photo.shape)).copy()
        window = photo_window(self.quad, self.photo.shape[:2])
        if window is None:
            return out[0] if single else out
        y0, y1, x0, x1 = window
        to_t = lambda a: torch.from_numpy(np.array(a, copy=True)).permute(0, 3, 1, 2).float() / 255.0
        # One warp for the mask and (ratio mode) the aligned input: they are the same for every frame.
        fixed = torch.cat([self._crop_mask(), to_t(self.aligned[None])], dim=1)
        fixed = self._warp(fixed, window)
        m, base = fixed[:, :1], fixed[:, 1:]
        photo = to_t(self.photo[None, y0:y1, x0:x1])
        with torch.no_grad():
            for start in range(0, len(relit), self.chunk):
                r = self._warp(to_t(relit[start:start + self.chunk]), window)
                if self.mode == "ratio":
                    gain = ((r + self.eps) / (base + self.eps)).clamp(0, self.max_gain)
                    r = (photo * gain).clamp(0, 1)
                blend = photo * (1 - m) + r * m
                px = (blend * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()
                out[start:start + len(px), y0:y1, x0:x1] = px
        return out[0] if single else out
