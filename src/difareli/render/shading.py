"""SH shading of a G-buffer: the shading reference R (SPEC 3) and albedo x irradiance renders."""

from __future__ import annotations

import numpy as np

from difareli.lighting import sh
from .raycast import GBuffer


def shading_reference(gbuffer: GBuffer, light, albedo: float = sh.SHADING_ALBEDO) -> np.ndarray:
    """Shading reference ``R = 0.7 * irradiance(light, normal)`` float32 HxWx3, unclipped, 0 off-mesh."""
    light = np.asarray(light, dtype=np.float32)
    r = sh.shading_reference(light, gbuffer.normal, mask=gbuffer.hit, albedo=albedo)
    return np.asarray(r, dtype=np.float32)


def render_sh(gbuffer: GBuffer, light, albedo, visibility=None) -> np.ndarray:
    """Lambertian render ``albedo * irradiance(light, normal) * visibility``, float32 HxWx3, 0 off-mesh.

    ``albedo``: HxWx3 map, a 3-vector or a scalar; ``visibility``: optional HxW multiplier (e.g. 1 minus a
    cast-shadow strength). Unclipped: irradiance of an SH light can be negative.
    """
    light = np.asarray(light, dtype=np.float32)
    irr = np.asarray(sh.irradiance(light, gbuffer.normal), dtype=np.float32)
    out = np.asarray(albedo, dtype=np.float32) * irr
    if visibility is not None:
        out = out * np.asarray(visibility, dtype=np.float32)[..., None]
    return np.where(gbuffer.hit[..., None], out, 0.0).astype(np.float32)
