"""Cast shadows from a depth map alone: march each visible point toward the light in screen space.

This is the inference-time shadow map of DiFaReli++ when no mesh is kept (SPEC 6: Hou et al., CVPR 2022,
march the depth map along the light direction). A point is shadowed when, somewhere along its ray toward the
light, the visible surface lies in front of the ray (closer to the viewer) by more than ``bias`` and less
than ``thickness``: surfaces hidden from the camera cannot occlude, and a ray passing far behind a thin
surface is not blocked (the depth map has no back faces). Orthographic DECA camera (docs/architecture.md).
"""

from __future__ import annotations

import numpy as np

from difareli.render.camera import OrthoCamera


def pixel_world_xy(cam: OrthoCamera, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-space x, y of every pixel centre (HxW each)."""
    u = (np.arange(width) + 0.5) / width * 2 - 1
    v = 1 - (np.arange(height) + 0.5) / height * 2
    x = u[None, :] / cam.scale - cam.tx
    y = v[:, None] / cam.scale - cam.ty
    return np.broadcast_to(x, (height, width)), np.broadcast_to(y, (height, width))


def march_shadow(depth: np.ndarray, hit: np.ndarray, cam: OrthoCamera, direction, *, max_distance: float = 2.0,
                 thickness: float = 0.5, bias_pixels: float = 0.5, normal: np.ndarray | None = None) -> np.ndarray:
    """Boolean HxW cast-shadow map of the visible surface ``depth`` (camera-space z where ``hit``) toward
    the unit light ``direction`` (camera space). Distances are in camera-space units (the mesh's units).

    With ``normal`` (HxWx3), only points facing the light (n.d > 0) can be in cast shadow; the rest are in
    attached shadow, which is not a cast shadow (as in ``render.cast_shadow``). The depth ``bias`` shortens
    shadows by ``bias * tan(angle to the view axis)``; 0.5 px shows no self-shadowing on a sphere.
    """
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    h, w = depth.shape
    pixel = 2.0 / (cam.scale * w)  # camera-space width of one pixel
    dxy = np.hypot(d[0], d[1])
    if dxy < 1e-6 or not hit.any():
        return np.zeros((h, w), bool)  # light along the view axis: nothing visible can occlude
    # One pixel of screen-space travel per step; stop after max_distance along the ray.
    step = pixel / dxy
    n_steps = int(min(np.ceil(max_distance / step), 2 * max(h, w)))
    x, y = pixel_world_xy(cam, h, w)
    cand = hit if normal is None else hit & (np.asarray(normal) @ d > 0)
    rows, cols = np.nonzero(cand)
    px, py, pz = x[rows, cols], y[rows, cols], depth[rows, cols].astype(np.float64)
    bias = bias_pixels * pixel
    shadow = np.zeros(rows.shape[0], bool)
    active = np.ones(rows.shape[0], bool)
    for k in range(1, n_steps + 1):
        s = k * step
        qx, qy, qz = px + s * d[0], py + s * d[1], pz + s * d[2]
        # Back to pixel indices (inverse of pixel_world_xy), nearest sample.
        j = np.floor(((qx + cam.tx) * cam.scale + 1) / 2 * w).astype(np.int64)
        i = np.floor((1 - (qy + cam.ty) * cam.scale) / 2 * h).astype(np.int64)
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
        active &= inside  # a ray that leaves the image is lit from there on
        if not active.any():
            break
        idx = np.nonzero(active)[0]
        ii, jj = i[idx], j[idx]
        surf = np.where(hit[ii, jj], depth[ii, jj], -np.inf)
        gap = surf - qz[idx]
        blocked = (gap > bias) & (gap < thickness)
        shadow[idx[blocked]] = True
        active[idx[blocked]] = False
    out = np.zeros((h, w), bool)
    out[rows, cols] = shadow
    return out
