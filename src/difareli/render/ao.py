"""Ambient occlusion by hemisphere rays on the mesh (SynthFaces v2).

``AO(p) = (1/pi) * integral over the hemisphere around n(p) of V(p, w) (n . w) dw``, estimated with
``rays`` cosine-weighted directions per pixel (so AO is the fraction of unblocked rays): 1 on an open plane,
< 1 in creases (eye sockets, nostrils, under the chin and the hair line), 0 inside a closed cavity.
``max_distance`` (relative to the mesh scale) makes it local: a blocker farther than that does not count
(``None``: any distance). The directions are a fixed stratified pattern turned by a per-pixel random
rotation from ``seed``, so a subject's AO is deterministic and computed once for all its lights.
"""

from __future__ import annotations

import math

import numpy as np

from .raycast import GBuffer, Scene
from .shadow import DEFAULT_EPS

from difareli.errors import UserError


def cosine_directions(rays: int) -> np.ndarray:
    """``(rays, 3)`` stratified cosine-weighted unit directions around +z (Fibonacci spiral on the disk)."""
    k = np.arange(rays) + 0.5
    r = np.sqrt(k / rays)
    phi = math.pi * (1 + 5**0.5) * k
    x, y = r * np.cos(phi), r * np.sin(phi)
    return np.stack([x, y, np.sqrt(np.maximum(0.0, 1 - x * x - y * y))], axis=-1)


def _frames(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Orthonormal tangents (t, b) for unit normals n (M, 3) (Frisvad-style, branch on the smaller axis).
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t = np.cross(n, a)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t)


def ambient_occlusion(scene: Scene, gbuffer: GBuffer, rays: int = 16, max_distance: float | None = 0.25,
                      seed: int = 0, eps: float = DEFAULT_EPS) -> np.ndarray:
    """AO ``(H, W)`` float32 in [0, 1] of the visible surface (1 off-mesh); see the module docstring."""
    if rays < 1:
        raise UserError(f"rays must be >= 1, got {rays}")
    hit = gbuffer.hit.reshape(-1)
    idx = np.flatnonzero(hit)
    out = np.ones(hit.shape, dtype=np.float32)
    if not len(idx):
        return out.reshape(gbuffer.shape)
    n = gbuffer.normal.reshape(-1, 3)[idx].astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    fn = gbuffer.face_normal.reshape(-1, 3)[idx].astype(np.float64)
    origins = gbuffer.points.reshape(-1, 3)[idx] + (eps * scene.scale) * fn
    t, b = _frames(n)
    # Per-pixel rotation of the pattern about the normal: decorrelates the stratification between pixels.
    ang = np.random.default_rng(seed).uniform(0, 2 * math.pi, len(idx))
    ca, sa = np.cos(ang)[:, None], np.sin(ang)[:, None]
    t, b = ca * t + sa * b, -sa * t + ca * b
    local = cosine_directions(rays)
    free = np.zeros(len(idx))
    limit = None if max_distance is None else float(max_distance) * scene.scale
    for d in local:
        w = d[0] * t + d[1] * b + d[2] * n
        if limit is None:
            blocked = scene.intersects_first(origins, w) >= 0
        else:
            blocked = _blocked_within(scene, origins, w, limit)
        free += ~blocked
    out[idx] = free / rays
    return out.reshape(gbuffer.shape)


def _blocked_within(scene: Scene, origins: np.ndarray, directions: np.ndarray, limit: float) -> np.ndarray:
    # First hit per ray with its location (embree), blocked when closer than ``limit``.
    blocked = np.zeros(len(origins), dtype=bool)
    tri, ray, loc = scene.intersector.intersects_id(origins, directions, multiple_hits=False, return_locations=True)
    if len(ray):
        dist = np.linalg.norm(loc - origins[ray], axis=1)
        blocked[ray[dist < limit]] = True
    return blocked
