"""Orthographic camera in DECA's convention (docs/architecture.md).

Camera space is right-handed, x right, y up, z toward the viewer. A point ``X`` maps to normalised device
coordinates ``ndc_xy = s * (X_xy + (tx, ty))`` in [-1, 1], then to continuous pixel coordinates
``u = (ndc_x + 1) / 2 * W`` (column, left to right) and ``v = (1 - ndc_y) / 2 * H`` (row, top down).
Pixel ``(row i, col j)`` covers ``[j, j+1) x [i, i+1)`` in ``(u, v)``, so its centre is ``(j + 0.5, i + 0.5)``.
Rays travel along -z; depth is the camera-space z (larger = nearer the viewer).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from difareli.errors import UserError

#: Direction of every primary ray (toward -z, away from the viewer).
RAY_DIRECTION = np.array([0.0, 0.0, -1.0])


@dataclass(frozen=True)
class OrthoCamera:
    """DECA orthographic camera ``cam = (scale, tx, ty)``."""

    scale: float
    tx: float = 0.0
    ty: float = 0.0

    def __post_init__(self):
        if not np.isfinite(self.scale) or self.scale == 0:
            raise UserError(f"OrthoCamera scale must be finite and non-zero, got {self.scale}")

    @classmethod
    def from_array(cls, cam) -> "OrthoCamera":
        """Camera from the 3-vector ``cam`` encoding ``(s, tx, ty)``."""
        cam = np.asarray(cam, dtype=np.float64).reshape(-1)
        if cam.shape != (3,):
            raise UserError(f"cam must have 3 entries (s, tx, ty), got shape {cam.shape}")
        return cls(float(cam[0]), float(cam[1]), float(cam[2]))

    def to_array(self) -> np.ndarray:
        """The ``cam`` encoding: float32 ``(s, tx, ty)``."""
        return np.array([self.scale, self.tx, self.ty], dtype=np.float32)

    def to_ndc(self, points) -> np.ndarray:
        """NDC ``(..., 2)`` of camera-space ``points (..., 3)`` (or ``(..., 2)``: z is ignored)."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * (p[..., :2] + np.array([self.tx, self.ty]))

    def project(self, points, H: int, W: int) -> np.ndarray:
        """Continuous pixel coordinates ``(..., 2)`` = ``(u, v)`` (column, row) of ``points (..., 3)``."""
        ndc = self.to_ndc(points)
        u = (ndc[..., 0] + 1.0) * 0.5 * W
        v = (1.0 - ndc[..., 1]) * 0.5 * H
        return np.stack([u, v], axis=-1)

    def unproject(self, uv, z, H: int, W: int) -> np.ndarray:
        """Camera-space points ``(..., 3)`` at pixel coordinates ``uv (..., 2)`` and depth ``z`` (broadcast)."""
        uv = np.asarray(uv, dtype=np.float64)
        ndc_x = 2.0 * uv[..., 0] / W - 1.0
        ndc_y = 1.0 - 2.0 * uv[..., 1] / H
        x = ndc_x / self.scale - self.tx
        y = ndc_y / self.scale - self.ty
        z = np.broadcast_to(np.asarray(z, dtype=np.float64), x.shape)
        return np.stack([x, y, z], axis=-1)

    def pixel_centers(self, H: int, W: int) -> np.ndarray:
        """Pixel-centre coordinates ``(H, W, 2)`` = ``(u, v)``, rows top-down."""
        v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
        return np.stack([u, v], axis=-1)

    def pixel_rays_within(self, H: int, W: int, z_start: float, lo, hi) -> tuple[np.ndarray, np.ndarray]:
        """The rows of :meth:`pixel_rays` whose origin's x, y lie in the box ``lo <= (x, y) <= hi``: their flat
        pixel indices (ascending) and origins ``(M, 3)``, the same values, without building every pixel's ray.
        A pixel's x depends on its column only and y on its row, so the box is a set of rows times columns."""
        u, v = np.arange(W) + 0.5, np.arange(H) + 0.5
        xs = (2.0 * u / W - 1.0) / self.scale - self.tx  # unproject's arithmetic, term for term
        ys = (1.0 - 2.0 * v / H) / self.scale - self.ty
        cols = np.flatnonzero((xs >= lo[0]) & (xs <= hi[0]))
        rows = np.flatnonzero((ys >= lo[1]) & (ys <= hi[1]))
        origins = np.empty((len(rows) * len(cols), 3))
        origins[:, 0] = np.tile(xs[cols], len(rows))
        origins[:, 1] = np.repeat(ys[rows], len(cols))
        origins[:, 2] = z_start
        return (rows[:, None] * W + cols[None, :]).ravel(), origins

    def pixel_rays(self, H: int, W: int, z_start: float) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays through pixel centres, row-major: origins ``(H*W, 3)`` at ``z = z_start``, and
        directions ``(H*W, 3)``, all ``(0, 0, -1)``."""
        origins = self.unproject(self.pixel_centers(H, W), z_start, H, W).reshape(-1, 3)
        directions = np.broadcast_to(RAY_DIRECTION, origins.shape).copy()
        return origins, directions
