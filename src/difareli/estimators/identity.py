"""Identity embedding: dlib's 128-d face descriptor (ResNet, LFW 99.38%) via ``face_recognition``.

The weights ship in ``face_recognition_models``; ArcFace (512-d, the paper's) needs downloads, so D = 128
here, as in SynthFaces. Descriptors of one person are < 0.6 apart (Euclidean), dlib's own threshold.
The face box is given from the FaceMesh landmarks, so dlib's HOG detector never runs. dlib is called directly
with exactly ``face_recognition.face_encodings``' calls (pose predictor on the box, then the ResNet descriptor),
loading only the two models it uses: importing ``face_recognition`` also loads the 68-point predictor and the
CNN detector, seconds of every photo's cold start spent on nothing.

``backend="torch"`` (default) runs the descriptor network as the PyTorch port of :mod:`.dlib_resnet` on the
150 px chip ``dlib.get_face_chip`` cuts (what ``compute_face_descriptor(image, shape)`` cuts itself): within
3e-7 of dlib's descriptor, ~15 ms instead of ~105 ms on one thread. ``backend="dlib"`` is the reference. dlib's
jitter (``num_jitters > 1``: random crops from dlib's own RNG) is not ported: it always runs on the dlib backend.
"""

from __future__ import annotations

import numpy as np

from difareli.errors import UserError

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

    def __init__(self, num_jitters: int = 1, model: str = "small", backend: str = "torch"):
        if model not in ("small", "large"):
            raise UserError(f"identity model must be 'small' (5 points) or 'large' (68 points), got {model!r}")
        if backend not in ("torch", "dlib"):
            raise UserError(f"identity backend must be 'torch' or 'dlib', got {backend!r}")
        self.num_jitters = num_jitters
        self.model = model
        self.backend = "dlib" if num_jitters > 1 else backend  # jitter: dlib's RNG, not ported
        self._models = None

    def models(self):
        """(pose predictor, face encoder), loaded on first use (face_recognition's model files); the encoder is
        dlib's for the dlib backend, :class:`~.dlib_resnet.DlibFaceResNet` for the torch one."""
        if self._models is None:
            import dlib
            import face_recognition_models as frm

            pose = (frm.pose_predictor_five_point_model_location() if self.model == "small"
                    else frm.pose_predictor_model_location())
            if self.backend == "torch":
                from .dlib_resnet import load

                encoder = load(frm.face_recognition_model_location())
            else:
                encoder = dlib.face_recognition_model_v1(frm.face_recognition_model_location())
            self._models = (dlib.shape_predictor(pose), encoder)
        return self._models

    def __call__(self, ctx: dict, needed: set[str]) -> dict:
        import dlib

        image = np.ascontiguousarray(ctx["image"])
        top, right, bottom, left = landmark_box(np.asarray(ctx["landmarks"])[:, :2], image.shape[:2])
        predictor, encoder = self.models()
        shape = predictor(image, dlib.rectangle(left, top, right, bottom))
        if self.backend == "torch":
            from .dlib_resnet import face_descriptors

            # The chip compute_face_descriptor(image, shape) cuts: get_face_chip_details(shape, 150, 0.25).
            enc = face_descriptors(dlib.get_face_chip(image, shape, size=150, padding=0.25), encoder)[0]
        else:
            enc = np.asarray(encoder.compute_face_descriptor(image, shape, self.num_jitters))
        if enc.shape != (IDENTITY_DIM,) or not np.isfinite(enc).all():
            raise BadInput("dlib produced no identity descriptor")
        return {"identity": enc.astype(np.float32)}
