"""Does a relight follow its target light and its target cast shadow? Closed-form per-image measures.

- **Lighting error** (:func:`light_error`): the SH light fitted to the relit image (:class:`LightFit`, with the
  source's normals and face parsing: the relit face keeps the input's geometry) against the target light the relight
  was asked for: the angle in degrees between their dominant directions (:func:`sh.dominant_direction`) and the
  relative SH error ``||l_fit - l_target|| / ||l_target||`` (Frobenius over the 9x3 coefficients). The fit carries
  the albedo prior's scale (``true albedo / prior``), so on protocol (ii) the relative error also holds the two
  subjects' albedo ratio; the angle does not depend on scale.
- **Shadow adherence** for a target shadow map M (binary, intersected with the face): the *darkening*
  ``D(img) = mean luminance(face \\ M) - mean luminance(face ∩ M)`` of the relit image, divided by the darkening the
  real cast shadow produces in the ground truth under the target light with the same M (1.0 for a perfect relight);
  and the IoU between the shadow :func:`detect_shadow` finds in the relit image and M. Both are NaN unless M covers
  at least ``min_share`` of the face and leaves at least that share lit (and, for the ratio, unless the ground
  truth darkens M by at least :data:`MIN_GT_DARKENING`).
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np

from difareli.lighting import sh
from difareli.lighting.light_fit import LightFit
from difareli.utils.imageops import luminance

#: The share of the face a target shadow must cover (and leave lit) for the shadow metrics to be defined.
MIN_SHARE = 0.05
#: Relative threshold of :func:`detect_shadow`: darker than the face's median luminance by more than this share.
DETECT_REL = 0.25
#: A ground truth that darkens M by less than this (luminance in [0, 1]) has no visible shadow to compare with.
MIN_GT_DARKENING = 1e-3
#: Encodings read as M, first found wins: the visibly shadowed pixels (SynthFaces v3), the exact cast map (v2), the
#: stored (estimated) map.
SHADOW_KEYS = ("shadow_visible_gt", "shadow_map_gt", "shadow_map")


def light_error(fitted: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """(angle in degrees between the dominant directions, ``||fitted - target|| / ||target||``)."""
    fitted, target = np.asarray(fitted, np.float64), np.asarray(target, np.float64)
    a, b = sh.dominant_direction(fitted), sh.dominant_direction(target)
    angle = math.degrees(math.acos(float(np.clip(a @ b, -1.0, 1.0))))
    return angle, float(np.linalg.norm(fitted - target) / max(np.linalg.norm(target), 1e-12))


def relit_light(relit: np.ndarray, geometry: Mapping[str, np.ndarray], fit: LightFit | None = None) -> np.ndarray:
    """The light ``fit`` (default :class:`LightFit`) finds in ``relit`` (uint8 HxWx3) on ``geometry``'s
    ``normal``, ``face_mask`` (and ``masks``)."""
    arrays = {k: v for k, v in geometry.items() if k in LightFit.ENCODINGS}
    return (fit or LightFit())({**arrays, "image": relit})


def relit_light_error(relit: np.ndarray, geometry: Mapping[str, np.ndarray], target: np.ndarray,
                      fit: LightFit | None = None) -> tuple[float, float]:
    """:func:`light_error` of :func:`relit_light` against ``target``."""
    return light_error(relit_light(relit, geometry, fit), target)


def face_luminance(image: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance in [0, 1] of a uint8 HxWx3 image."""
    return luminance(np.asarray(image, np.float64) / 255.0)


def detect_shadow(image: np.ndarray, face: np.ndarray, rel: float = DETECT_REL) -> np.ndarray:
    """The shadow found in a uint8 image: face pixels whose luminance is below ``(1 - rel) * median`` of the face's
    luminance (bool HxW). A cast shadow removes a share of the light, so it is a relative drop, not an absolute one."""
    face = np.asarray(face, bool)
    lum = face_luminance(image)
    if not face.any():
        return np.zeros_like(face)
    return face & (lum < (1.0 - rel) * float(np.median(lum[face])))


def darkening(image: np.ndarray, face: np.ndarray, m: np.ndarray) -> float:
    """Mean luminance of the face outside ``m`` minus inside it (NaN when either side is empty)."""
    face, m = np.asarray(face, bool), np.asarray(m, bool)
    lum = face_luminance(image)
    inside, outside = face & m, face & ~m
    if not inside.any() or not outside.any():
        return math.nan
    return float(lum[outside].mean() - lum[inside].mean())


def shadow_share(face: np.ndarray, m: np.ndarray) -> float:
    """The share of the face's pixels in ``m`` (NaN for an empty face)."""
    face = np.asarray(face, bool)
    n = int(face.sum())
    return float((face & np.asarray(m, bool)).sum() / n) if n else math.nan


def shadow_scores(relit: np.ndarray, gt: np.ndarray, face: np.ndarray, m: np.ndarray, *, min_share: float = MIN_SHARE,
                  rel: float = DETECT_REL) -> dict[str, float]:
    """``{shadow_adherence, shadow_darkening, shadow_iou}`` of a relit image against target shadow ``m`` on ``face``,
    the ground truth ``gt`` under the target light giving the real shadow's darkening; NaN where undefined."""
    face = np.asarray(face, bool)
    m = np.asarray(m, bool) & face
    share = shadow_share(face, m)
    nan = {"shadow_adherence": math.nan, "shadow_darkening": math.nan, "shadow_iou": math.nan}
    if not (share >= min_share and 1.0 - share >= min_share):
        return nan
    raw, real = darkening(relit, face, m), darkening(gt, face, m)
    found = detect_shadow(relit, face, rel)
    iou = float((found & m).sum() / max((found | m).sum(), 1))
    ratio = raw / real if real >= MIN_GT_DARKENING else math.nan
    return {"shadow_adherence": ratio, "shadow_darkening": raw, "shadow_iou": iou}


def target_shadow(arrays: Mapping[str, np.ndarray]) -> tuple[np.ndarray | None, str | None]:
    """(binary M, the encoding it came from) of a record's arrays (:data:`SHADOW_KEYS`), or (None, None)."""
    for key in SHADOW_KEYS:
        if key in arrays:
            return np.asarray(arrays[key]) > 0, key
    return None, None
