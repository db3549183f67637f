"""Identity embedding: dlib's 128-d face descriptor (ResNet, LFW 99.38%) via ``face_recognition``.

The weights ship in ``face_recognition_models``; ArcFace (512-d, the paper's) needs downloads, so D = 128
here, as in SynthFaces. Descriptors of one person are < 0.6 apart (Euclidean), dlib's own threshold.
The face box is given from the FaceMesh landmarks, so dlib's HOG detector never runs. dlib is called directly
with exactly ``face_recognition.face_encodings``' calls (pose predictor on the box, then the ResNet descriptor),
loading only the two models it uses: importing ``face_recognition`` also loads the 68-point predictor and the
CNN detector, seconds of every photo's cold start spent on nothing.

``backend="torch"`` (default) runs the descriptor network as the PyTorch port of :mod:`.dlib_resnet` on the
150 px chip ``dlib.get_face_chip`` cuts (what ``compute_face_descriptor(image, shape)`` cuts itself): within
3e-7 of dlib's descriptor, ~15 ms instead of ~105 ms on one thread; a folder's run (:meth:`DlibIdentity.batch`) runs
it on :data:`BATCH` chips at a time. ``backend="dlib"`` is the reference. dlib's
jitter (``num_jitters > 1``: random crops from dlib's own RNG) is not ported: it always runs on the dlib backend.
"""

from __future__ import annotations

import numpy as np

from difareli.errors import UserError

from .loading import BadInput

IDENTITY_DIM = 128
#: Chips per network call in :meth:`DlibIdentity.batch`: 5.8 ms per chip against 13.0 one at a time (one thread, the
#: 2-core EPYC under load, scripts/bench_preprocess.py's machine).
BATCH = 8


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

    def shape(self, ctx: dict):
        """dlib's 5- (or 68-) point shape of the face, predicted in the box around the crop's landmarks."""
        import dlib

        image = np.ascontiguousarray(ctx["image"])
        top, right, bottom, left = landmark_box(np.asarray(ctx["landmarks"])[:, :2], image.shape[:2])
        return image, self.models()[0](image, dlib.rectangle(left, top, right, bottom))

    def chip(self, ctx: dict) -> np.ndarray:
        """The 150 px chip ``compute_face_descriptor(image, shape)`` cuts itself:
        ``get_face_chip_details(shape, 150, 0.25)``."""
        import dlib

        image, shape = self.shape(ctx)
        return dlib.get_face_chip(image, shape, size=150, padding=0.25)

    def __call__(self, ctx: dict, needed: set[str]) -> dict:
        if self.backend == "torch":
            from .dlib_resnet import face_descriptors

            enc = face_descriptors(self.chip(ctx), self.models()[1])[0]
        else:
            image, shape = self.shape(ctx)
            enc = np.asarray(self.models()[1].compute_face_descriptor(image, shape, self.num_jitters))
        return _checked(enc)

    def batch(self, ctxs: list[dict], needed: set[str]) -> list[dict | Exception]:
        """:meth:`__call__` of several crops, the network run on :data:`BATCH` chips at a time (zeros fill the
        last group): a descriptor then depends on its chip alone, never on which photos share its batch (oneDNN
        picks other kernels for 1-3 images, whose results differ by ~2e-7). Within 3e-7 of the one-chip call."""
        if self.backend != "torch":
            return [_guarded(self, ctx, needed) for ctx in ctxs]
        from .dlib_resnet import CHIP, face_descriptors

        chips: list = []
        for ctx in ctxs:
            try:
                chips.append(self.chip(ctx))
            except Exception as e:  # noqa: BLE001 - one photo's failure is its own entry
                chips.append(e)
        ok = [i for i, c in enumerate(chips) if not isinstance(c, Exception)]
        out: list = list(chips)
        for start in range(0, len(ok), BATCH):
            group = ok[start:start + BATCH]
            x = np.zeros((BATCH, CHIP, CHIP, 3), np.uint8)
            x[:len(group)] = [chips[i] for i in group]
            enc = face_descriptors(x, self.models()[1], batch_size=BATCH)
            for j, i in enumerate(group):
                out[i] = _guarded(_checked, enc[j])
        return out


def _checked(enc: np.ndarray) -> dict:
    enc = np.asarray(enc)
    if enc.shape != (IDENTITY_DIM,) or not np.isfinite(enc).all():
        raise BadInput("dlib produced no identity descriptor")
    return {"identity": enc.astype(np.float32)}


def _guarded(fn, *args):
    """``fn(*args)``, or the exception it raised (a batch's entry for that photo)."""
    try:
        return fn(*args)
    except Exception as e:  # noqa: BLE001 - one photo's failure is its own entry
        return e
