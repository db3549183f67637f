"""Detections past the photo's edge (issue 61's phantom face): a box running past the edge is clipped and kept
only where FaceMesh finds a face in it, so the largest box the aligner keeps is a real face. The detector and
FaceMesh are replaced by fixed answers: the rule, not mediapipe, is under test."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.estimators.align import PAST_EDGE, FaceAligner, clip_box, inside_boxes

pytest.importorskip("cv2")

H, W = 200, 300
REAL = np.array([60.0, 50.0, 60.0, 70.0])  # a real face, inside the photo
PHANTOM = np.array([228.0, 40.0, 100.0, 110.0])  # 28 px past the right edge, over no face: the largest box
CUT = np.array([-10.0, 120.0, 50.0, 60.0])  # a real face the left edge cuts


def centre(box: np.ndarray) -> np.ndarray:
    return np.array([box[0] + box[2] / 2, box[1] + box[3] / 2])


def aligner(boxes: list[np.ndarray], faces: list[np.ndarray]) -> FaceAligner:
    """An aligner whose detector answers ``boxes`` and whose FaceMesh finds a face at the centre of the first of
    ``faces`` inside the crop it is given (as FaceMesh finds the nearest real face in a wide crop)."""
    a = FaceAligner(size=64, models=(0,))
    a._run = lambda model, rgb, scale, offset: [(0.9, np.array(b)) for b in boxes]

    def landmarks(rgb, box):
        for f in faces:
            c = centre(f)
            if box is None or (box[0] - box[2] <= c[0] <= box[0] + 2 * box[2]
                               and box[1] - box[3] <= c[1] <= box[1] + 2 * box[3]):
                return np.tile([*c, 0.0], (478, 1))
        return None

    a.landmarks = landmarks
    return a


def test_clip_box_says_how_much_lies_inside():
    clipped, share = clip_box(PHANTOM, (H, W))
    np.testing.assert_allclose(clipped, [228, 40, 72, 110])
    assert share == pytest.approx(0.72)
    assert clip_box(REAL, (H, W))[1] == 1.0


def test_a_box_past_the_edge_over_no_face_is_refused_and_the_real_face_wins():
    rgb = np.zeros((H, W, 3), np.uint8)
    found = aligner([PHANTOM, REAL], [REAL]).detect(rgb)
    assert len(found) == 1
    np.testing.assert_allclose(found[0][1], REAL)
    # Before the rule the phantom was the largest box, and the default relit it.
    assert PHANTOM[2] * PHANTOM[3] > REAL[2] * REAL[3]


def test_a_real_face_the_edge_cuts_is_kept_clipped():
    rgb = np.zeros((H, W, 3), np.uint8)
    found = aligner([CUT, PHANTOM], [CUT]).detect(rgb)
    assert len(found) == 1
    np.testing.assert_allclose(found[0][1], [0, 120, 40, 60])
    # A box barely past the edge (under PAST_EDGE of it) needs no confirmation.
    nudge = np.array([W - 50.0 * (1 - PAST_EDGE / 2), 10.0, 50.0, 50.0])
    kept = inside_boxes([(0.9, nudge)], (H, W), lambda b: False)
    assert len(kept) == 1 and kept[0][1][0] + kept[0][1][2] == pytest.approx(W)
