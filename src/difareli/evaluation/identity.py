"""Identity similarity of a relit face: the cosine of dlib's 128-d face descriptor (the one the package ships as
:class:`difareli.estimators.identity.DlibIdentity`, run as its PyTorch port :mod:`difareli.estimators.dlib_resnet`).

The descriptor network was trained on 150 px chips that dlib cuts around 5 landmarks (``get_face_chip(image, shape,
150, 0.25)``). A 64 px SynthFaces face is ~35 px wide, so each image is first upsampled (bicubic) until its face box
is at least :data:`MIN_BOX` px wide, dlib's 5-point shape predictor is run in the face box (the bounding box of the
record's face mask: brows to chin, what dlib's detector boxes), and the chip is cut from the upsampled image. Each
image is aligned on its own (relit, input and ground truth), as identity metrics of face images are computed.

The weights are those of the photo extras (``face_recognition_models`` and ``dlib``, installed by
``DIFARELI_PREPROCESS=1 scripts/install.sh``): without them :func:`unavailable` says why and the identity columns are
left out of every table (never a fake value).
"""

from __future__ import annotations

import functools
import os

import numpy as np

from difareli.errors import UserError

#: The face box is upsampled to at least this width before the shape predictor and the 150 px chip.
MIN_BOX = 150
CHIP, PADDING = 150, 0.25


@functools.lru_cache(maxsize=1)
def unavailable() -> str | None:
    """None when the descriptor can run, else one line saying what is missing and how to install it."""
    try:
        import dlib  # noqa: F401
        import face_recognition_models as frm

        path = frm.face_recognition_model_location()
        pose = frm.pose_predictor_five_point_model_location()
    except Exception as e:  # ImportError, or pkg_resources missing under setuptools >= 81
        return (f"identity columns left out: dlib's face descriptor is not installed ({type(e).__name__}: "
                f"{str(e)[:80]}); install the photo extras: DIFARELI_PREPROCESS=1 scripts/install.sh")
    missing = [p for p in (path, pose) if not os.path.isfile(p)]
    if missing:
        return f"identity columns left out: the descriptor's weight files are missing ({', '.join(missing)})"
    return None


@functools.lru_cache(maxsize=1)
def _models():
    import dlib
    import face_recognition_models as frm

    from difareli.estimators.dlib_resnet import load

    return (dlib.shape_predictor(frm.pose_predictor_five_point_model_location()),
            load(frm.face_recognition_model_location()))


def face_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(left, top, right, bottom) of the mask's pixels; a ValueError for an empty mask."""
    ys, xs = np.nonzero(np.asarray(mask, dtype=bool))
    if ys.size == 0:
        raise UserError("identity: empty face mask, no face box")
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def chip(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The aligned 150x150 uint8 chip of a uint8 HxWx3 face whose face region is ``mask`` (see the module doc)."""
    import dlib
    import torch
    import torch.nn.functional as F

    image = np.asarray(image, dtype=np.uint8)
    left, top, right, bottom = face_box(mask)
    scale = max(1, int(np.ceil(MIN_BOX / max(right - left, bottom - top))))
    if scale > 1:  # bicubic on float, clipped back to 8 bits (what the predictor and the network read)
        x = torch.from_numpy(image.astype(np.float32)).permute(2, 0, 1)[None]
        x = F.interpolate(x, scale_factor=scale, mode="bicubic", align_corners=False)
        image = x[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()
    image = np.ascontiguousarray(image)
    predictor, _ = _models()
    shape = predictor(image, dlib.rectangle(left * scale, top * scale, right * scale, bottom * scale))
    return dlib.get_face_chip(image, shape, size=CHIP, padding=PADDING)


def descriptors(images: list[np.ndarray], masks: list[np.ndarray]) -> np.ndarray:
    """(N, 128) descriptors of uint8 faces, each aligned in its own mask's box (one batched network pass)."""
    from difareli.estimators.dlib_resnet import face_descriptors

    return face_descriptors(np.stack([chip(i, m) for i, m in zip(images, masks)]), _models()[1])


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    """Cosine similarity of two descriptors (1 for identical ones)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))


def similarities(relit: np.ndarray, relit_mask: np.ndarray, others: dict[str, tuple[np.ndarray, np.ndarray]]
                 ) -> dict[str, float]:
    """``{name: cosine(relit, image)}`` for each ``name: (image, mask)`` of ``others``."""
    names = list(others)
    d = descriptors([relit, *(others[n][0] for n in names)], [relit_mask, *(others[n][1] for n in names)])
    return {n: cosine(d[0], d[k + 1]) for k, n in enumerate(names)}
