"""Cast shadows from a depth map alone: march each visible point toward the light in screen space.

This is the inference-time shadow map of DiFaReli++ when no mesh is kept (SPEC 6: Hou et al., CVPR 2022,
march the depth map along the light direction). A point is shadowed when, somewhere along its ray toward the
light, the visible surface lies in front of the ray (closer to the viewer) by more than ``bias`` and less
than ``thickness``: surfaces hidden from the camera cannot occlude, and a ray passing far behind a thin
surface is not blocked (the depth map has no back faces). Orthographic DECA camera (docs/architecture.md).

Two things decide its quality (measured on SynthFaces v3 against mesh ray casting, scripts/shadow_map_quality.py):

- which points may be in cast shadow at all: only those facing the light, as in ``render.cast_shadow``; a
  point facing away is in attached shadow, and a ray from it dives into its own surface at once. Where no
  normal is known the march estimates one from the depth map (:func:`depth_normals`); without that test half
  of its marks on a face were attached shadow on the hair, skull and neck.
- how the surface between pixel centres is read: ``sample="plane"`` (default) takes the nearest pixel's depth
  extended along its own tangent plane (:func:`depth_gradient`), exact on planes (no staircase self-shadowing,
  so no depth bias is needed) while a depth step stays a step halfway between the pixels (a hair or hat edge
  keeps its one-pixel shadow, which bilinear reads smooth away). ``"nearest"`` is the plain pixel depth.
"""

from __future__ import annotations

import numpy as np

from difareli.errors import UserError
from difareli.render.camera import OrthoCamera

#: How the march reads the surface between pixel centres (see the module doc).
SAMPLES = ("plane", "nearest")


def pixel_world_xy(cam: OrthoCamera, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-space x, y of every pixel centre (HxW each)."""
    u = (np.arange(width) + 0.5) / width * 2 - 1
    v = 1 - (np.arange(height) + 0.5) / height * 2
    x = u[None, :] / cam.scale - cam.tx
    y = v[:, None] / cam.scale - cam.ty
    return np.broadcast_to(x, (height, width)), np.broadcast_to(y, (height, width))


def depth_gradient(depth: np.ndarray, hit: np.ndarray, cam: OrthoCamera) -> tuple[np.ndarray, np.ndarray]:
    """``(dz/dx, dz/dy)`` of the visible surface at every pixel (camera space: y up), HxW each, 0 off ``hit``.

    Per axis, of the two one-sided differences to neighbours on the mesh the one of smaller magnitude: a
    depth step beside a pixel (a silhouette, a hair or hat edge) does not tilt it. Measured against central
    differences and against taking the central one where both sides agree: this is the best lit test.
    """
    h, w = depth.shape
    z = np.pad(np.where(hit, depth, np.nan).astype(np.float64), 1, constant_values=np.nan)
    c = z[1:-1, 1:-1]

    def smaller(a, b):
        return np.nan_to_num(np.where(np.isnan(a), b, np.where(np.isnan(b) | (np.abs(a) < np.abs(b)), a, b)))

    gx = smaller(z[1:-1, 2:] - c, c - z[1:-1, :-2]) * (cam.scale * w / 2)
    gy = smaller(z[:-2, 1:-1] - c, c - z[2:, 1:-1]) * (cam.scale * h / 2)  # row - 1 is +y
    return np.where(hit, gx, 0.0), np.where(hit, gy, 0.0)


def depth_normals(depth: np.ndarray, hit: np.ndarray, cam: OrthoCamera) -> np.ndarray:
    """Unit camera-space normals (HxWx3, 0 off ``hit``) of the depth map, from :func:`depth_gradient`."""
    gx, gy = depth_gradient(depth, hit, cam)
    n = np.stack([-gx, -gy, np.ones_like(gx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(hit[..., None], n, 0.0)


def march_shadow(depth: np.ndarray, hit: np.ndarray, cam: OrthoCamera, direction, *, max_distance: float = 2.0,
                 thickness: float = 0.5, bias_pixels: float = 0.0, normal: np.ndarray | None = None,
                 sample: str = "plane", estimate_normals: bool = True) -> np.ndarray:
    """Boolean HxW cast-shadow map of the visible surface ``depth`` (camera-space z where ``hit``) toward
    the unit light ``direction`` (camera space). Distances are in camera-space units (the mesh's units).

    Only points facing the light (n.d > 0) can be in cast shadow; the rest are in attached shadow, which is not
    a cast shadow (as in ``render.cast_shadow``). ``normal`` (HxWx3) gives n where it is known (|n| > 0.5);
    elsewhere, with ``estimate_normals``, n is estimated from the depth map (:func:`depth_normals`), else every
    point is marched. The depth ``bias`` shortens shadows by ``bias * tan(angle to the view axis)``.
    """
    return march_shadows(depth, hit, cam, np.asarray(direction, dtype=np.float64)[None], max_distance=max_distance,
                         thickness=thickness, bias_pixels=bias_pixels, normal=normal, sample=sample,
                         estimate_normals=estimate_normals)[0]


def _ray_starts(dirs: np.ndarray, untested: np.ndarray, tested: np.ndarray, facing: np.ndarray, pixel: float,
                max_distance: float) -> list[tuple[int, np.ndarray, float, int]]:
    """Per direction that can cast a visible shadow: its index, the flat pixels whose rays it marches (those
    whose normal is not tested, and those facing it), its step (one pixel of screen-space travel) and step count
    (``max_distance`` along the ray, at most twice the image's side)."""
    h, w = untested.shape
    starts = []
    for n, d in enumerate(dirs):
        dxy = np.hypot(d[0], d[1])
        if dxy < 1e-6:
            continue  # light along the view axis: nothing visible can occlude
        flat = np.flatnonzero(untested | (tested & (facing @ d > 0)))
        step = pixel / dxy
        if len(flat):
            starts.append((n, flat, step, int(min(np.ceil(max_distance / step), 2 * max(h, w)))))
    return starts


def march_shadows(depth: np.ndarray, hit: np.ndarray, cam: OrthoCamera, directions, *, max_distance: float = 2.0,
                  thickness: float = 0.5, bias_pixels: float = 0.0, normal: np.ndarray | None = None,
                  sample: str = "plane", estimate_normals: bool = True) -> np.ndarray:
    """:func:`march_shadow` toward each of N light ``directions`` (Nx3) at once: an NxHxW boolean stack.

    Every ray of every direction advances one pixel of screen-space travel per step in one set of array
    operations, and rays that are blocked, leave the image or reach ``max_distance`` are dropped as they finish,
    so N maps (a video's targets) cost about as much array work as their rays, not N times the per-step overhead.
    """
    if sample not in SAMPLES:
        raise UserError(f"sample={sample!r}: use one of {SAMPLES}")
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
    bias = bias_pixels * pixel
    # Where the lit test reads a normal: the given one where known, else the depth map's own.
    known = np.zeros(hit.shape, bool) if normal is None else np.linalg.norm(normal, axis=-1) > 0.5
    facing = np.where(known[..., None], normal, 0.0) if normal is not None else np.zeros((h, w, 3))
    if estimate_normals and not known[hit].all():
        facing = np.where(known[..., None], facing, depth_normals(depth, hit, cam))
    test = known | (estimate_normals & hit)
    if sample == "plane":
        gx, gy = depth_gradient(depth, hit, cam)
        gx, gy, xs, ys = gx.ravel(), gy.ravel(), x.ravel(), y.ravel()
        # The highest a tangent plane reaches inside its own pixel.
        reach = surface + (np.abs(gx) + np.abs(gy * w / h)) * (pixel / 2)
    else:
        reach = surface
    # A ray rising toward the viewer (dz >= 0) at or above the highest surface less the bias can never be blocked
    # again (blocking needs surface - z > bias): it is dropped there, which ends most lit rays early.
    top = reach.max() - bias
    starts = _ray_starts(dirs, hit & ~test, hit & test, facing, pixel, max_distance)
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
        # Back to pixel indices (inverse of pixel_world_xy): the nearest pixel centre.
        j = np.floor(((qx + cam.tx) * cam.scale + 1) / 2 * w).astype(np.int64)
        i = np.floor((1 - (qy + cam.ty) * cam.scale) / 2 * h).astype(np.int64)
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)  # a ray that leaves the image is lit from there on
        f = np.where(inside, i * w + j, 0)
        if sample == "plane":  # that pixel's depth, carried along its tangent plane to the ray's point
            gap = surface[f] + gx[f] * (qx - xs[f]) + gy[f] * (qy - ys[f]) - qz
        else:
            gap = surface[f] - qz
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
