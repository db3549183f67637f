"""Visibly shadowed: the pixels whose cast shadows take a large share of their light (SynthFaces v3's
``shadow_visible_gt``), from any per-sun cast masks: the renderer's mesh rays or the depth-map march.

A cast shadow from a weak fill light barely darkens a pixel the key sun still lights; a binary map that marks it
asks a model to draw a shadow the image does not have. So a pixel counts as visibly shadowed when the suns it
cannot see carry more than ``threshold`` of its unshadowed light (:func:`shadow_fraction`), or when it is in the
key sun's own cast shadow. :func:`visible_shadow` is that rule (the ground truth's, on the mesh's casts);
:func:`visible_march` applies it to the march's casts toward every sun of a light (``lighting.suns.Suns``):
the one shadow-map maker's answer when the light's suns are known.
"""

from __future__ import annotations

import numpy as np

from difareli.lighting.suns import Suns
from difareli.render.camera import OrthoCamera
from difareli.render.screen_shadow import depth_normals, march_shadows
from difareli.utils.imageops import LUMA

#: The march's cut on the share of light the blocked suns carry. Lower than the ground truth's 0.25
#: (``SynthConfig.shadow_visible``) because the march misses part of the fill and rim suns' casts; chosen on the
#: val split of an unseen-seed v3 store over 0.05-0.3 (IoU 0.665 at 0.15 against 0.641 at 0.25: docs/shadow_maps.md).
MARCH_VISIBLE = 0.15


def shadow_fraction(e_open: np.ndarray, sun_terms, casts, hit: np.ndarray) -> np.ndarray:
    """Per pixel, the share of its unshadowed irradiance ``e_open`` (HxWx3) that the cast shadows remove:
    ``sum_i cast_i Y(sun_i) / Y(e_open)`` in [0, 1], 0 off ``hit`` (float32 HxW)."""
    den = np.maximum(e_open @ LUMA, 1e-6)
    frac = np.zeros(hit.shape, np.float64)
    for sun, c in zip(sun_terms, casts):
        frac += c * ((sun @ LUMA) / den)
    return np.where(hit, np.clip(frac, 0.0, 1.0), 0.0).astype(np.float32)


def visible_shadow(e_open: np.ndarray, sun_terms, casts, key: np.ndarray, hit: np.ndarray,
                   threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """(fraction, visible): :func:`shadow_fraction` and ``fraction > threshold | key`` (the key sun's own cast
    mask) on ``hit``."""
    frac = shadow_fraction(e_open, sun_terms, casts, hit)
    return frac, hit & ((frac > threshold) | key)


def visible_march(depth: np.ndarray, normal: np.ndarray | None, cam: OrthoCamera, suns: Suns,
                  threshold: float = MARCH_VISIBLE) -> np.ndarray:
    """The visibly shadowed pixels (bool HxW) of the surface ``depth`` (0 = no surface) under ``suns``: the march
    toward every sun, weighed by :func:`visible_shadow`. ``normal`` (HxWx3, zero where unknown) decides which
    points face each sun and how much light each sun gives them (the depth map's own normals elsewhere). Under
    an SH light's single sun (``Suns.of_sh``) this is the march's cast map itself."""
    depth = np.asarray(depth, np.float64)
    hit = depth != 0
    casts = march_shadows(depth, hit, cam, suns.dirs, normal=normal)
    n = depth_normals(depth, hit, cam)
    if normal is not None:
        normal = np.asarray(normal, np.float64)
        n = np.where((np.linalg.norm(normal, axis=-1) > 0.5)[..., None], normal, n)
    terms = suns.terms(n)
    e_open = suns.irradiance(n)
    return visible_shadow(e_open, terms, casts, casts[0], hit, threshold)[1]
