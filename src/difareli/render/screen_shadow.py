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
    return march_shadows(depth, hit, cam, np.asarray(direction, dtype=np.float64)[None], max_distance=max_distance,
                         thickness=thickness, bias_pixels=bias_pixels, normal=normal)[0]


def march_shadows(depth: np.ndarray, hit: np.ndarray, cam: OrthoCamera, directions, *, max_distance: float = 2.0,
                  thickness: float = 0.5, bias_pixels: float = 0.5, normal: np.ndarray | None = None) -> np.ndarray:
    """:func:`march_shadow` toward each of N light ``directions`` (Nx3) at once: an NxHxW boolean stack.

    Every ray of every direction advances one pixel of screen-space travel per step in one set of array
    operations, and rays that are blocked, leave the image or reach ``max_distance`` are dropped as they finish,
    so N maps (a video's targets) cost about as much array work as their rays, not N times the per-step overhead.
    """
    dirs = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    h, w = depth.shape
    out = np.zeros((len(dirs), h, w), bool)
    if not hit.any():
        return out
    pixel = 2.0 / (cam.scale * w)  # camera-space width of one pixel
    x, y = pixel_world_xy(cam, h, w)
    # The visible surface, -inf off it (nothing there occludes), as one flat array to gather from.
    surface = np.where(hit, depth, -np.inf).astype(np.float64).ravel()
    normal = None if normal is None else np.asarray(normal)
    bias = bias_pixels * pixel
    # A ray rising toward the viewer (dz >= 0) at or above the highest surface less the bias can never be blocked
    # again (blocking needs surface - z > bias): it is dropped there, which ends most lit rays early.
    top = surface.max() - bias
    starts = []  # per direction: the pixels whose rays it marches
    for n, d in enumerate(dirs):
        dxy = np.hypot(d[0], d[1])
        if dxy < 1e-6:
            continue  # light along the view axis: nothing visible can occlude
        cand = hit if normal is None else hit & (normal @ d > 0)
        flat = np.flatnonzero(cand)
        step = pixel / dxy  # one pixel of screen-space travel per step; stop after max_distance along the ray
        n_steps = int(min(np.ceil(max_distance / step), 2 * max(h, w)))
        if len(flat):
            starts.append((n, flat, step, n_steps))
    if not starts:
        return out
    ray_dir = np.concatenate([np.repeat(n, len(f)) for n, f, _, _ in starts])
    ray_pix = np.concatenate([f for _, f, _, _ in starts])
    ray_step = np.concatenate([np.full(len(f), s) for _, f, s, _ in starts])
    ray_last = np.concatenate([np.full(len(f), k) for _, f, _, k in starts])
    px, py, pz = x.ravel()[ray_pix], y.ravel()[ray_pix], depth.ravel()[ray_pix].astype(np.float64)
    dx, dy, dz = dirs[ray_dir, 0], dirs[ray_dir, 1], dirs[ray_dir, 2]
    ids = np.arange(len(ray_pix))
    shadow = np.zeros(len(ray_pix), bool)
    for k in range(1, int(ray_last.max()) + 1):
        s = k * ray_step
        qx, qy, qz = px + s * dx, py + s * dy, pz + s * dz
        # Back to pixel indices (inverse of pixel_world_xy), nearest sample.
        j = np.floor(((qx + cam.tx) * cam.scale + 1) / 2 * w).astype(np.int64)
        i = np.floor((1 - (qy + cam.ty) * cam.scale) / 2 * h).astype(np.int64)
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)  # a ray that leaves the image is lit from there on
        gap = surface[np.where(inside, i * w + j, 0)] - qz
        blocked = inside & (gap > bias) & (gap < thickness)
        shadow[ids[blocked]] = True
        # A ray in screen space leaves the (convex) image once and for all, so dropping it loses nothing.
        keep = inside & ~blocked & (ray_last > k) & ~((dz >= 0) & (qz >= top))
        if not keep.any():
            break
        if not keep.all():
            ids, px, py, pz, dx, dy, dz, ray_step, ray_last = (
                a[keep] for a in (ids, px, py, pz, dx, dy, dz, ray_step, ray_last))
    out.reshape(len(dirs), -1)[ray_dir[shadow], ray_pix[shadow]] = True
    return out
