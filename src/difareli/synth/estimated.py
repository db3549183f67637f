"""Model inputs as a user has them, estimated from a SynthFaces record's rendered image.

``inputs: estimated`` (SynthFaces v3, :func:`estimate_all`): **every** model input comes from the photo
estimators of ``difareli-preprocess`` (``estimators.pipeline.default_estimators``: FaceMesh + BFM fit for
``shape``/``cam`` and the face surface, FaceMesh outlines + selfie segmentation for ``masks``/``face_mask``/
``background``, dlib for ``identity``), then the record light fit and the shadow classifier on that estimated geometry:

- A SynthFaces render is already a face crop, so :class:`FrameAligner` keeps its frame (no FFHQ re-crop): every
  estimated map lies in the stored image's pixels and the ground-truth pairs stay aligned.
- The estimators run on the image rendered at ``estimation_resolution`` (default: the stored resolution; the
  BFM geometry estimator upsamples anything below 192 px for FaceMesh itself). The estimated surface is then
  rendered at the stored resolution through the estimated camera (``cam`` is in NDC, so no resampling of normals
  or depth is needed) and the part labels are resampled by the mode of each block.
- ``light``: :class:`difareli.lighting.light_fit.LightFit` on the stored (estimated) arrays, the fit
  ``difareli-benchmark`` makes on that record; ``shading`` its shading reference on the estimated normals;
  ``shadow``/``shadow_map``: :class:`difareli.estimators.shadow.ShadowEstimator` on the estimated surface. The map is
  stored binary until the store's c range is known (``synth/c_norm.py`` scales it once the store is complete).

``inputs: estimated_light`` (SynthFaces v2, :func:`estimate_inputs`): only ``light``, ``shading``, ``shadow`` and
``shadow_map`` are estimated; geometry, masks and identity are the renderer's.
The exact values are kept under ``*_gt`` either way.
"""

from __future__ import annotations

import importlib.util

import numpy as np

from difareli.lighting import sh
from difareli.data.encodings import FACE_PARTS, FOREGROUND_PARTS, NUM_MASK_PARTS, PART_INDEX
from difareli.errors import UserError
from difareli.estimators.loading import BadInput
from difareli.lighting.light_fit import LightFit
from difareli.render import OrthoCamera, render_gbuffer

_SHADOW = None
_FACE_IDX = np.array([PART_INDEX[p] for p in FACE_PARTS])
_FG_IDX = np.array([PART_INDEX[p] for p in FOREGROUND_PARTS])
#: What the photo pipeline is asked for (the rest is derived at the stored resolution).
PIPELINE_ENCODINGS = ("shape", "cam", "identity", "masks", "face_mask", "normal")  # normal: the surface
#: The model inputs that hold estimates in a v3 store; their exact values are under ``<name>_gt``.
ESTIMATED = ("light", "shading", "shadow", "shadow_map", "shape", "cam", "identity", "masks", "face_mask",
             "background", "normal", "depth")
FIX = "install the photo estimators (DIFARELI_PREPROCESS=1 bash scripts/install.sh) or generate inputs=estimated_light"


class FrameAligner:
    """An aligner that keeps the frame: the image is already the crop (a SynthFaces render), returned as it is."""

    def __init__(self, size: int):
        self.size = int(size)

    def __call__(self, rgb: np.ndarray) -> dict:
        h, w = rgb.shape[:2]
        if (h, w) != (self.size, self.size):
            raise UserError(f"FrameAligner({self.size}) got a {h}x{w} image")
        quad = np.array([[0, 0], [0, h], [w, h], [w, 0]], dtype=np.float64)
        return {"image": rgb, "quad": quad, "faces": 1, "box": None, "notes": []}


def shadow_estimator():
    """The preprocess shadow estimator with its shipped weights (loaded once per process)."""
    global _SHADOW
    if _SHADOW is None:
        from difareli.estimators.shadow import ShadowEstimator

        _SHADOW = ShadowEstimator()
    return _SHADOW


def missing_estimators() -> str | None:
    """Why the photo estimators cannot run here (a sentence naming the fix), or None."""
    gone = [m for m in ("mediapipe", "cv2", "face_recognition", "dlib") if importlib.util.find_spec(m) is None]
    return f"inputs=estimated needs the photo estimators ({', '.join(gone)} not installed); {FIX}" if gone else None


def pipeline(size: int):
    """The preprocess pipeline (default estimators, frame-keeping aligner) at ``size`` px, once per process."""
    from difareli.estimators.pipeline import default_pipeline

    try:
        return default_pipeline(["image", *PIPELINE_ENCODINGS], size,
                                align={"_target_": f"{__name__}.FrameAligner", "size": size})
    except ImportError as e:
        raise ImportError(f"SynthFaces inputs=estimated runs the photo estimators ({e}); {FIX}") from e


def mode_downsample(labels: np.ndarray, size: int) -> np.ndarray:
    """A label map resampled to ``size`` x ``size`` by the most frequent label of each block (nearest when the
    sizes do not divide)."""
    h = labels.shape[0]
    if h == size:
        return labels
    if h % size:
        idx = ((np.arange(size) + 0.5) * h / size).astype(int)
        return labels[np.ix_(idx, idx)]
    f = h // size
    onehot = np.eye(NUM_MASK_PARTS, dtype=np.int32)[labels.reshape(size, f, size, f)]
    return onehot.sum((1, 3)).argmax(-1).astype(np.uint8)


def estimate_light_and_shadow(arrays: dict, region: np.ndarray, gbuffer, scene) -> tuple[dict, dict]:
    """``light`` (LightFit on the stored ``image``/``normal``/``face_mask``/``masks``), ``shading`` on ``region``,
    ``shadow``/``shadow_map`` (the classifier on ``gbuffer``/``scene``, map = cast * fixed-range normalised c) and
    meta. Raises ValueError when the light fit has too few usable skin pixels."""
    fit = LightFit()
    light = fit({k: arrays[k] for k in LightFit.ENCODINGS}).astype(np.float32)
    shading = np.asarray(sh.shading_reference(light, arrays["normal"], mask=region), dtype=np.float32)
    ctx = {"image": arrays["image"], "gbuffer": gbuffer, "scene": scene, "light": light,
           "skin": np.asarray(arrays["masks"]) == PART_INDEX["skin"], "albedo_prior": fit.prior()}
    out = shadow_estimator()(ctx, set())
    info = {"c_logit": round(out["shadow_info"]["logit"], 6), "p_shadow": round(out["shadow_info"]["p_shadow"], 6)}
    return {"light": light, "shading": shading, "shadow": out["shadow"].astype(np.float32),
            "shadow_map": out["shadow_map"].astype(np.float32), "cast": out["cast"]}, info


def estimate_inputs(arrays: dict, region: np.ndarray, gbuffer, scene) -> tuple[dict, dict]:
    """SynthFaces v2 (``inputs=estimated_light``): estimated light/shading/shadow/shadow_map on exact geometry."""
    est, info = estimate_light_and_shadow(arrays, region, gbuffer, scene)
    est.pop("cast")
    return est, info


def estimate_all(image: np.ndarray, est_image: np.ndarray | None = None) -> tuple[dict, dict]:
    """Every model input of a v3 record from its stored ``image`` (HxWx3 uint8) alone; ``est_image`` is the same
    render at the estimation resolution (None: ``image`` itself). Returns (arrays, meta); ``shadow_map`` is the
    binary cast map (scaled by the store's c range later). Raises ValueError naming the failing estimator."""
    big = image if est_image is None else est_image
    try:
        got, meta, ctx = pipeline(big.shape[0]).process(np.ascontiguousarray(big))
    except BadInput as e:
        raise UserError(f"photo estimators: {e}") from None
    H, W = image.shape[:2]
    cam = np.asarray(got["cam"], np.float32)
    gb = render_gbuffer(ctx["scene"], OrthoCamera(*cam.tolist()), H, W)
    normal = np.where(gb.hit[..., None], gb.normal, 0.0).astype(np.float32)
    masks = mode_downsample(np.asarray(got["masks"], np.uint8), H)
    arrays = {"image": image, "shape": np.asarray(got["shape"], np.float32), "cam": cam,
              "identity": np.asarray(got["identity"], np.float32), "masks": masks,
              "face_mask": np.isin(masks, _FACE_IDX), "normal": normal,
              "depth": np.where(gb.hit, gb.depth, 0.0).astype(np.float32),
              "background": np.where(np.isin(masks, _FG_IDX)[..., None], 0, image).astype(np.uint8)}
    est, info = estimate_light_and_shadow(arrays, gb.hit, gb, ctx["scene"])
    arrays.update(est, shadow_map=est["cast"].astype(np.float32))  # binary until the store's c range is known
    # No timings in record meta: a record must not depend on the machine's load (resumed and sharded stores equal
    # the unsharded one byte for byte); the generator reports the rate.
    info["estimation"] = {"resolution": int(big.shape[0]), "bfm_fit": meta.get("bfm_fit")}
    return {k: arrays[k] for k in ESTIMATED}, info
