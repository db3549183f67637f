"""Shared image operations: kornia's median filter equals scipy's zero-padded one on masks; luminance weights."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import median_filter

from difareli.utils.imageops import LUMA, luminance, median_mask


@pytest.mark.parametrize("share", [0.2, 0.5, 0.8])
@pytest.mark.parametrize("size", [1, 3, 5, 7])
def test_median_mask_matches_scipy_zero_padded(share, size):
    rng = np.random.default_rng(int(share * 10) + size)
    masks = rng.random((3, 29, 41)) < share
    want = np.stack([median_filter(m.astype(np.uint8), size=size, mode="constant", cval=0).astype(bool)
                     for m in masks])
    np.testing.assert_array_equal(median_mask(masks, size), want)
    np.testing.assert_array_equal(median_mask(masks[0], size), want[0])  # one (H, W) mask


def test_median_mask_refuses_an_even_window():
    with pytest.raises(ValueError, match="odd"):
        median_mask(np.zeros((4, 4), bool), 4)


def test_luminance_is_rec709():
    assert LUMA.sum() == pytest.approx(1.0)
    rgb = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.5, 0.5]])
    np.testing.assert_allclose(luminance(rgb), [0.2126, 0.7152, 0.0722, 0.5])


def test_rgb2lab_u8_is_scikit_images_rgb2lab_bit_for_bit():
    from skimage.color import rgb2lab

    from difareli.utils.imageops import rgb2lab_u8

    rng = np.random.default_rng(0)
    pixels = rng.integers(0, 256, (5000, 3), dtype=np.uint8)
    grey = np.repeat(np.arange(256, dtype=np.uint8)[:, None], 3, axis=1)  # both sides of the 0.04045 knee
    for rgb in (pixels, grey, pixels.reshape(50, 100, 3)):
        np.testing.assert_array_equal(rgb2lab_u8(rgb), rgb2lab(rgb))
    # White is L = 100, a = b = 0 up to the matrix's rounding (its rows sum to D65 to 4 digits).
    np.testing.assert_allclose(rgb2lab_u8(np.array([[255, 255, 255]], np.uint8)), [[100, 0, 0]], atol=1e-2)
    with pytest.raises(ValueError, match="uint8 RGB"):
        rgb2lab_u8(pixels.astype(np.float64))
