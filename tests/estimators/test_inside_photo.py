"""``align.inside_photo`` on broadcast rows and columns equals the full-grid computation it replaced, bit for bit."""

from __future__ import annotations

import numpy as np

from difareli.estimators.align import inside_photo


def _full_grid(quad: np.ndarray, size: int, hw: tuple[int, int]) -> np.ndarray:
    """The computation before the speed-up: every pixel centre's photo coordinates on a (size, size, 2) grid."""
    quad = np.asarray(quad, dtype=np.float64)
    v, u = np.mgrid[0:size, 0:size] + 0.5
    xy = quad[0] + u[..., None] * (quad[3] - quad[0]) / size + v[..., None] * (quad[1] - quad[0]) / size
    return (xy[..., 0] >= 0) & (xy[..., 0] <= hw[1]) & (xy[..., 1] >= 0) & (xy[..., 1] <= hw[0])


def test_inside_photo_equals_the_full_grid():
    rng = np.random.default_rng(0)
    partly = 0
    for _ in range(200):
        c, a, r = rng.uniform(-100, 700, 2), rng.uniform(0, 2 * np.pi), rng.uniform(20, 600)
        x = np.array([np.cos(a), np.sin(a)]) * r
        y = np.array([-x[1], x[0]])
        quad = np.stack([c - x - y, c - x + y, c + x + y, c + x - y])
        size, hw = int(rng.choice([64, 96, 256])), (int(rng.integers(64, 900)), int(rng.integers(64, 900)))
        got = inside_photo(quad, size, hw)
        np.testing.assert_array_equal(got, _full_grid(quad, size, hw))
        partly += 0 < got.mean() < 1
    assert partly > 50  # most quads straddle the photo's edge: the comparison is not all-True or all-False
    # A quad shifted by half a pixel puts column 63's centres exactly on the photo's left edge (x = 0): inside.
    quad = np.array([[-63.5, 0], [-63.5, 128], [64.5, 128], [64.5, 0]])
    got = inside_photo(quad, 128, (128, 128))
    np.testing.assert_array_equal(got, _full_grid(quad, 128, (128, 128)))
    assert got[:, 63].all() and not got[:, 62].any()
