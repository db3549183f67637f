"""Identity embedding: dlib's 128-d face descriptor (ResNet, LFW 99.38%) via ``face_recognition``.

The weights ship in ``face_recognition_models``; ArcFace (512-d, the paper's) needs downloads, so D = 128
here, as in SynthFaces. Descriptors of one person are < 0.6 apart (Euclidean), dlib's own threshold.
The face box is given from the FaceMesh landmarks, so dlib's HOG detector never runs.
"""

from __future__ import annotations

import numpy as np

from .loading import BadInput

IDENTITY_DIM = 128


def landmark_box(lm_xy: np.ndarray, shape: tuple[int, int], pad: float = 0.05) -> tuple[int, int, int, int]:
    """dlib-style (top, right, bottom, left) box around the landmarks, padded by ``pad`` of its size."""
    x0, y0 = lm_xy.min(0)
    x1, y1 = lm_xy.max(0)
    px, py = pad * (x1 - x0), pad * (y1 - y0)
    H, W = shape
    return (int(max(0, y0 - py)), int(min(W - 1, x1 + px)), int(min(H - 1, y1 + py)), int(max(0, x0 - px)))


class DlibIdentity:
    """Estimator: ``identity`` (128,) float32."""

    provides = ("identity",)
    requires = ("image", "landmarks")

    def __init__(self, num_jitters: int = 1, model: str = "small"):
        self.num_jitters = num_jitters
        self.model = model

    def __call__(self, ctx: dict, needed: set[str]) -> dict:
        import face_recognition

        image = np.ascontiguousarray(ctx["image"])
        box = landmark_box(np.asarray(ctx["landmarks"])[:, :2], image.shape[:2])
        enc = face_recognition.face_encodings(image, known_face_locations=[box], num_jitters=self.num_jitters,
                                              model=self.model)
        if not enc:
            raise BadInput("dlib produced no identity descriptor")
        return {"identity": np.asarray(enc[0], dtype=np.float32)}
