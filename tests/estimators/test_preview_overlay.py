"""The preview's mesh overlay drawn at once equals drawing skimage's lines edge by edge, pixel for pixel."""

from __future__ import annotations

import numpy as np
from skimage.draw import line

from difareli.estimators.preview import mesh_overlay, segment_pixels


def _one_by_one(image, landmarks_xy, triangles):
    """The overlay before the speed-up: one skimage line per edge, blended in place."""
    out = image.copy()
    H, W = out.shape[:2]
    edges = {tuple(sorted(e)) for t in triangles for e in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))}
    pts = np.round(np.asarray(landmarks_xy) - 0.5).astype(int)
    for a, b in edges:
        rr, cc = line(pts[a, 1], pts[a, 0], pts[b, 1], pts[b, 0])
        ok = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
        out[rr[ok], cc[ok]] = (0.4 * out[rr[ok], cc[ok]] + 0.6 * np.array([0, 255, 0])).astype(np.uint8)
    return out


def test_segment_pixels_are_skimage_lines():
    rng = np.random.default_rng(0)
    seg = rng.integers(-40, 300, (3000, 4))
    seg[:30, 2:] = seg[:30, :2]  # single points
    seg[30:60, 2] = seg[30:60, 0]  # horizontal
    seg[60:90, 3] = seg[60:90, 1]  # vertical
    seg[90:120, 2:] = seg[90:120, :2] + rng.integers(-50, 50, (30, 1))  # diagonals: |dr| = |dc|
    rr, cc = segment_pixels(*seg.T)
    n = np.abs(seg[:, 2:] - seg[:, :2]).max(1)
    start, ends = np.r_[0, np.cumsum(n)[:-1]], n.sum()
    for k, (r0, c0, r1, c1) in enumerate(seg):
        want = line(r0, c0, r1, c1)
        got_r = np.r_[rr[start[k]:start[k] + n[k]], rr[ends + k]]
        got_c = np.r_[cc[start[k]:start[k] + n[k]], cc[ends + k]]
        np.testing.assert_array_equal(got_r, want[0], err_msg=str(seg[k]))
        np.testing.assert_array_equal(got_c, want[1], err_msg=str(seg[k]))


def test_mesh_overlay_equals_drawing_edge_by_edge():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (96, 96, 3), dtype=np.uint8)
    points = rng.uniform(-20, 116, (60, 2))  # some outside the image: clipped
    triangles = rng.integers(0, 60, (150, 3))  # shared edges: pixels blended several times
    before = image.copy()
    got = mesh_overlay(image, points, triangles)
    np.testing.assert_array_equal(got, _one_by_one(image, points, triangles))
    assert (got != image).any(axis=-1).mean() > 0.2 and np.array_equal(image, before)  # drawn on a copy
