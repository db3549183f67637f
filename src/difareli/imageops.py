"""Image operations shared across the package: Rec. 709 luminance and median filtering (kornia).

One definition of the luminance weights (SynthFaces' shadow strength, the light fit's residuals, the shadow
classifier's features, difference maps and the video shadow rule all weigh colour the same way). Median
filtering goes through kornia's ``median_blur`` (zero padding, as scipy's ``mode="constant", cval=0``).
"""

from __future__ import annotations

import numpy as np

#: Rec. 709 luminance weights of linear RGB.
LUMA = np.array([0.2126, 0.7152, 0.0722])


def luminance(rgb: np.ndarray) -> np.ndarray:
    """``(..., 3)`` linear RGB -> ``(...)`` Rec. 709 luminance (float64)."""
    return np.asarray(rgb, dtype=np.float64) @ LUMA


def median_mask(mask: np.ndarray, size: int) -> np.ndarray:
    """A boolean mask (H, W) or a batch (B, H, W) median-filtered with a ``size`` x ``size`` window (odd),
    outside the image counted as ``False``: a pixel stays set where most of its window is set."""
    import kornia
    import torch

    if size % 2 == 0 or size < 1:
        raise ValueError(f"median window must be odd and positive, got {size}")
    m = np.asarray(mask, dtype=bool)
    x = torch.from_numpy(m.reshape(-1, 1, *m.shape[-2:]).astype(np.float32))
    return (kornia.filters.median_blur(x, (size, size), border_type="constant") > 0.5).numpy().reshape(m.shape)
