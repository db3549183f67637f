"""Crops that run past the photo's edge: the padding is reflected, never a constant block, and the
composite's mask does not fade at the photo's edge; forehead skin above FaceMesh's oval is skin, not hair/hat."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.data.encodings import PART_INDEX
from difareli.estimators.align import inside_photo, warp_quad
from difareli.relight.composite import Compositor

from tests.helpers import HAS_CV2, HAS_ESTIMATORS

# The alignment warp is OpenCV's, which only the photo extras install (the README's plain install has none).
needs_cv2 = pytest.mark.skipif(not HAS_CV2,
                               reason="needs OpenCV (the photo extras: DIFARELI_PREPROCESS=1 bash scripts/install.sh)")
S = 64


def ramp_photo(h=120, w=160):
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([40 + x, 40 + y, 100 + (x + y) // 4], -1).clip(0, 255).astype(np.uint8)


@needs_cv2
def test_padding_is_a_reflection_not_a_block():
    photo = ramp_photo()
    quad = np.array([[30.0, -40.0], [30.0, 80.0], [150.0, 80.0], [150.0, -40.0]])  # a third above the top edge
    inside = inside_photo(quad, S, photo.shape[:2])
    assert 0.3 < 1 - inside.mean() < 0.36
    crop = warp_quad(photo, quad, S).astype(int)
    band = crop[~inside.all(1)]
    # A ramp reflected at the edge varies along the band as the photo does: no constant block.
    assert band[..., 1].std() > 5
    rows = np.nonzero(~inside.all(1))[0]
    e = rows.max() + 1  # the first crop row inside the photo; the row k above it mirrors the row k below
    np.testing.assert_allclose(crop[e - 3, :, 1], crop[e + 2, :, 1], atol=2.5)
    zeros = warp_quad(photo, quad, S, border="zeros")
    assert (zeros[~inside] == 0).mean() > 0.9


@needs_cv2
def test_composite_mask_reaches_the_photo_edge():
    photo = ramp_photo()
    quad = np.array([[30.0, -40.0], [30.0, 80.0], [150.0, 80.0], [150.0, -40.0]])
    aligned = warp_quad(photo, quad, S)
    labels = np.zeros((S, S), np.uint8)
    labels[:, 16:48] = PART_INDEX["skin"]
    inside = inside_photo(quad, S, photo.shape[:2])
    labels_masked = np.where(inside, labels, 0).astype(np.uint8)  # the padded band labelled background
    plain = Compositor(photo, aligned, labels_masked, quad).mask()
    fixed = Compositor(photo, aligned, labels_masked, quad, inside=inside).mask()
    # Without the fill the feather fades the blend at the photo's top row; with it the face reaches the edge.
    assert plain[0, 70:110].mean() < 0.8
    assert fixed[0, 70:110].min() > 0.99


@pytest.mark.skipif(not HAS_ESTIMATORS, reason="needs the photo estimators")
def test_forehead_above_the_oval_is_skin_on_a_tight_crop():
    """The astronaut cut just above the brows: the reflected forehead was a hat block; now no hat, and the
    forehead skin above the FaceMesh oval is skin."""
    import skimage.data

    from difareli.relight import photo

    rgb = np.ascontiguousarray(skimage.data.astronaut()[70:])
    prepared = photo.prepare_photo(rgb, ["image", "light"], size=S)
    assert prepared.past_edge > 0.1
    lab = prepared.arrays["masks"]
    assert (lab == PART_INDEX["hat"]).sum() == 0
    inside_rows = np.nonzero(prepared.inside.all(1))[0]
    top = lab[inside_rows[0]:inside_rows[0] + 4, 24:40]
    assert (top == PART_INDEX["skin"]).mean() > 0.5, top
