"""png_bytes: any reader decodes the pixels written, for every colour type and shape."""

from __future__ import annotations

import io

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from difareli.utils.png import png_bytes


@pytest.mark.parametrize("shape", [(1, 1), (37, 53), (5, 7, 1), (64, 96, 3), (1, 300, 3), (300, 1, 4), (33, 17, 4)])
def test_png_round_trip(shape):
    rng = np.random.default_rng(sum(shape))
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    img.reshape(-1)[: img.size // 3] = 255  # runs as well as noise; wrap-around in the Up filter both ways
    data = png_bytes(img)
    want = img[..., 0] if img.ndim == 3 and img.shape[2] == 1 else img
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(data))), want)
    np.testing.assert_array_equal(iio.imread(data, extension=".png"), want)


def test_png_levels_are_lossless_and_compress():
    y, x = np.mgrid[:128, :128]
    img = np.stack([x, y, (x + y) // 2], -1).astype(np.uint8)  # smooth: the Up filter leaves small numbers
    sizes = []
    for level in (0, 1, 9):
        data = png_bytes(img, level)
        np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(data))), img)
        sizes.append(len(data))
    assert sizes[0] > img.size and sizes[1] < img.size / 10 and sizes[2] <= sizes[1]


@pytest.mark.parametrize("bad", [np.zeros((4, 4), np.float32), np.zeros((4, 4, 2), np.uint8),
                                 np.zeros((0, 4), np.uint8), np.zeros((2, 2, 2, 3), np.uint8)])
def test_png_refuses_what_it_cannot_write(bad):
    with pytest.raises(ValueError, match="uint8"):
        png_bytes(bad)
