"""Cast-shadow maps by secondary rays toward a directional light (SPEC 6, inference maps).

A pixel is in *cast* shadow when the ray from its visible surface point toward the light hits other
geometry. Only points that face the light cast a ray: a point whose smooth normal or whose facet normal
points away from the light (``n . d <= 0``) is in *attached* shadow, which the SH shading reference already
darkens, so it is not a cast shadow here. Requiring the facet normal to face the light too is what keeps a
convex mesh free of cast shadows at its terminator: a ray leaving a facet into its outer half-space cannot
re-enter a convex polyhedron.
"""

from __future__ import annotations

import numpy as np

from .raycast import GBuffer, Scene

from difareli.errors import UserError

#: Shadow-ray origins are lifted off the surface by this fraction of the mesh scale (bounding-box
#: diagonal) along the facet normal, well above embree's float32 resolution, to avoid self-hits ("acne").
DEFAULT_EPS = 1e-4


def _unit_direction(direction) -> np.ndarray:
    d = np.asarray(direction, dtype=np.float64).reshape(-1)
    if d.shape != (3,):
        raise UserError(f"direction must be a 3-vector, got shape {d.shape}")
    norm = np.linalg.norm(d)
    if not np.isfinite(norm) or norm == 0:
        raise UserError(f"direction must be finite and non-zero, got {d}")
    return d / norm


def lit_candidates(gbuffer: GBuffer, direction) -> np.ndarray:
    """Bool HxW: hit pixels whose smooth and facet normals both face the light (``n . d > 0``); the
    complement within ``hit`` is attached shadow."""
    d = _unit_direction(direction).astype(np.float32)
    return gbuffer.hit & (gbuffer.normal @ d > 0) & (gbuffer.face_normal @ d > 0)


def cast_shadow(scene: Scene, gbuffer: GBuffer, direction, eps: float = DEFAULT_EPS) -> np.ndarray:
    """Bool HxW cast-shadow map: True where the ray from the visible point toward the unit light
    ``direction`` (camera space, pointing *to* the light) is blocked by ``scene``.

    ``gbuffer`` may come from a different scene than the occluders (e.g. shadows of invisible geometry).
    """
    d = _unit_direction(direction)
    cand = lit_candidates(gbuffer, d).reshape(-1)
    idx = np.flatnonzero(cand)
    out = np.zeros(cand.shape, dtype=bool)
    if len(idx):
        p = gbuffer.points.reshape(-1, 3)[idx]
        fn = gbuffer.face_normal.reshape(-1, 3)[idx].astype(np.float64)
        origins = p + (eps * scene.scale) * fn
        blocked = scene.intersects_first(origins, np.broadcast_to(d, origins.shape)) >= 0
        out[idx] = blocked
    return out.reshape(gbuffer.shape)


def cast_shadows(scene: Scene, gbuffer: GBuffer, directions, eps: float = DEFAULT_EPS) -> np.ndarray:
    """Cast-shadow maps ``(L, H, W)`` for ``L`` light directions ``(L, 3)``.

    One ray query per light: merging the lights into one query is slower with embree (cache misses).
    """
    dirs = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((len(dirs), *gbuffer.shape), dtype=bool)
    for i, d in enumerate(dirs):
        out[i] = cast_shadow(scene, gbuffer, d, eps)
    return out
