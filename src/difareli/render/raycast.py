"""Primary-ray G-buffer of a camera-space triangle mesh (trimesh + embree).

A :class:`Scene` wraps one mesh in camera space, its per-triangle labels, precomputed normals and a single
ray intersector (one BVH), so the primary render and every shadow pass of a subject reuse the same build.
:func:`render_gbuffer` casts one orthographic ray per pixel centre (``OrthoCamera.pixel_rays``) and
returns a :class:`GBuffer`.

Off-mesh conventions: ``hit`` False, ``normal``/``face_normal``/``points``/``bary`` 0, ``depth`` ``-inf``
(camera z grows toward the viewer, so "infinitely far behind"; ``np.maximum`` z-compositing works
unchanged), ``label`` 0 (``MASK_PARTS[0] == "background"``), ``triangle`` -1.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import trimesh

from .camera import RAY_DIRECTION, OrthoCamera

from difareli.errors import UserError

#: Primary rays start this far (relative to the mesh scale) in front of the nearest vertex.
_RAY_START_MARGIN = 0.05
#: Rays per intersector call.
_RAY_CHUNK = 65536


def _make_intersector(mesh: trimesh.Trimesh, backend: str):
    """Embree intersector if available (or requested), else trimesh's pure-Python one, with a warning."""
    if backend not in ("auto", "embree", "python"):
        raise UserError(f"backend must be 'auto', 'embree' or 'python', got {backend!r}")
    if backend in ("auto", "embree"):
        if trimesh.ray.has_embree:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            return RayMeshIntersector(mesh), "embree"
        if backend == "embree":
            raise RuntimeError("backend='embree' requested but embreex is not importable (pip install embreex)")
        warnings.warn(
            "embreex is not available: falling back to trimesh's pure-Python ray tracer (~50x slower)",
            RuntimeWarning,
            stacklevel=3,
        )
    from trimesh.ray.ray_triangle import RayMeshIntersector

    return RayMeshIntersector(mesh), "python"


def _normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit facet normals (F, 3) (0 for degenerate faces, right-hand winding) and area-weighted unit vertex
    normals (V, 3); computed here because trimesh's angle-weighted version dominates a Scene build."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    face_normals = _unit(cross)[0]
    # Each face adds its area-weighted normal to its three vertices.
    V = len(vertices)
    summed = np.stack(
        [sum(np.bincount(faces[:, k], weights=cross[:, c], minlength=V) for k in range(3)) for c in range(3)],
        axis=-1,
    )
    return face_normals, _unit(summed)[0]


class Scene:
    """A camera-space triangle mesh with per-triangle int ``labels`` (F,) and one ray intersector.

    ``labels`` default to 1 for every triangle; label 0 is reserved for "background" in the G-buffer but
    may also be given to triangles (e.g. a backdrop). ``vertex_normals`` (V, 3) override the default
    area-weighted average of facet normals. ``backend``: ``"auto"`` (embree if installed), ``"embree"`` or
    ``"python"``. The Scene snapshots the geometry: build a new one if the mesh changes.
    """

    def __init__(self, mesh: trimesh.Trimesh, labels=None, *, vertex_normals=None, backend: str = "auto"):
        faces = np.asarray(mesh.faces, dtype=np.int64)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise UserError(f"Scene needs a non-empty triangle mesh, got faces of shape {faces.shape}")
        if labels is None:
            labels = np.ones(len(faces), dtype=np.int32)
        labels = np.asarray(labels)
        if labels.shape != (len(faces),) or not np.issubdtype(labels.dtype, np.integer):
            raise UserError(f"labels must be ints of shape ({len(faces)},), got {labels.dtype} {labels.shape}")
        if labels.min() < 0:
            raise UserError("labels must be non-negative (0 is background)")
        self.mesh = mesh
        self.labels = labels.astype(np.int32)
        # Plain float64 copies: trimesh's cached properties re-hash arrays on each access.
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64).copy()
        self.faces = faces.copy()
        self.face_normals, self.vertex_normals = _normals(self.vertices, self.faces)
        if vertex_normals is not None:
            vn = np.asarray(vertex_normals, dtype=np.float64)
            if vn.shape != self.vertices.shape:
                raise UserError(f"vertex_normals must have shape {self.vertices.shape}, got {vn.shape}")
            self.vertex_normals = _unit(vn)[0]
        #: Length of the bounding-box diagonal; offsets (ray starts, shadow eps) are relative to it.
        self.scale = float(np.linalg.norm(np.ptp(self.vertices, axis=0))) or 1.0
        # Per-face tables so a render gathers once per hit instead of re-deriving per pixel.
        self._corner_z = self.vertices[self.faces, 2]  # (F, 3)
        self._corner_normals = self.vertex_normals[self.faces]  # (F, 3, 3)
        self._bary_affine, self._edge_on = _xy_barycentric_affine(self.vertices[self.faces])
        self.intersector, self.backend = _make_intersector(mesh, backend)
        # Build the BVH now so that render timings measure rays only.
        self.intersects_first(np.zeros((1, 3)), np.array([[0.0, 0.0, -1.0]]))

    @classmethod
    def from_arrays(cls, vertices, faces, labels=None, *, vertex_normals=None, backend: str = "auto") -> "Scene":
        """Scene from raw ``vertices (V, 3)`` and ``faces (F, 3)``; the arrays are kept as given
        (no vertex merging), so ``labels`` and face indices stay aligned."""
        mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), process=False)
        return cls(mesh, labels, vertex_normals=vertex_normals, backend=backend)

    @property
    def num_faces(self) -> int:
        """Number of triangles."""
        return len(self.faces)

    def intersects_first(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Index of the first triangle each ray ``(N, 3)`` hits, -1 on a miss (directions need not be unit)."""
        out = np.empty(len(origins), dtype=np.int64)
        # Chunked: embree queries get superlinearly slower past ~1e5 rays per call (cache misses).
        for i in range(0, len(origins), _RAY_CHUNK):
            sl = slice(i, i + _RAY_CHUNK)
            out[sl] = self.intersector.intersects_first(origins[sl], directions[sl])
        return out


@dataclass
class GBuffer:
    """Per-pixel render of a :class:`Scene` (all HxW, rows top-down; see the module doc for off-mesh values).

    ``normal``: smooth unit normal (barycentric interpolation of vertex normals), oriented toward the viewer
    side of the hit triangle; ``face_normal``: the hit triangle's geometric unit normal, same orientation;
    ``depth``: camera z of the hit; ``points``: float64 hit positions; ``bary``: barycentric coordinates in
    the hit triangle; ``label``: the triangle's label; ``triangle``: its index.
    """

    hit: np.ndarray
    normal: np.ndarray
    face_normal: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    bary: np.ndarray
    label: np.ndarray
    triangle: np.ndarray
    cam: OrthoCamera

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.hit.shape


def _xy_barycentric_affine(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-triangle affine maps ``(F, 6)`` (two rows of 3) from ``(x, y, 1)`` to barycentrics ``(b1, b2)`` of
    the triangles' xy projection, and a mask of triangles seen exactly edge-on (no xy area; their map is 0).

    Exact for rays along -z: an orthographic projection is affine, and affine maps keep barycentrics.
    """
    a = tri[:, 0, :2]
    e1, e2 = tri[:, 1, :2] - a, tri[:, 2, :2] - a
    den = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ref = max(1.0, float(np.abs(tri).max(initial=1.0))) ** 2
    edge_on = np.abs(den) < 1e-14 * ref
    inv = np.where(edge_on, 0.0, 1.0 / np.where(edge_on, 1.0, den))
    # b1 = cross(p - a, e2) / den, b2 = cross(e1, p - a) / den, written as rows acting on (x, y, 1).
    r1 = np.stack([e2[:, 1], -e2[:, 0], -(a[:, 0] * e2[:, 1] - a[:, 1] * e2[:, 0])], axis=-1)
    r2 = np.stack([-e1[:, 1], e1[:, 0], -(e1[:, 0] * a[:, 1] - e1[:, 1] * a[:, 0])], axis=-1)
    return (np.concatenate([r1, r2], axis=1) * inv[:, None]), edge_on


def _barycentric(scene: "Scene", tri: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Barycentrics ``(M, 3)`` of ray points ``xy (M, 2)`` in hit triangles ``tri (M,)``."""
    aff = scene._bary_affine[tri]  # (M, 6): rows (b1, b2) x coefficients of (x, y, 1)
    x, y = xy[:, 0], xy[:, 1]
    bary = np.empty((len(tri), 3))
    # Elementwise, not batched matmul: numpy's (M, 2, 3) @ (M, 3, 1) is several times slower.
    bary[:, 1] = aff[:, 0] * x + aff[:, 1] * y + aff[:, 2]
    bary[:, 2] = aff[:, 3] * x + aff[:, 4] * y + aff[:, 5]
    bary[:, 0] = 1.0 - bary[:, 1] - bary[:, 2]
    # Edge-on triangles (embree rarely reports them) get their centroid.
    bary[scene._edge_on[tri]] = 1.0 / 3.0
    # Embree works in float32 and can report hits a hair outside an edge: clamp back into the triangle.
    np.maximum(bary, 0.0, out=bary)
    bary /= bary.sum(axis=1, keepdims=True)
    return bary


def _unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0), n[..., 0]


def render_gbuffer(scene: Scene, cam: OrthoCamera, H: int, W: int, *, cull: bool = True) -> GBuffer:
    """Cast one ray per pixel centre of an ``H x W`` image along -z and return the :class:`GBuffer`.

    ``cull``: cast only the rays through the mesh's xy bounding box (one pixel of margin for embree's float32 edge
    tests); a ray along -z outside it cannot hit, so the G-buffer is the same, for a fraction of the rays (a face
    fills ~40% of an FFHQ crop). ``cull=False`` casts every ray (the reference the tests compare with)."""
    if isinstance(cam, (np.ndarray, list, tuple)):
        cam = OrthoCamera.from_array(cam)
    z_start = scene.vertices[:, 2].max() + _RAY_START_MARGIN * scene.scale
    if cull:
        margin = 2.0 / (cam.scale * W)  # one pixel in camera-space units
        lo, hi = scene.vertices[:, :2].min(0) - margin, scene.vertices[:, :2].max(0) + margin
        rays, origins = cam.pixel_rays_within(H, W, z_start, lo, hi)
    else:
        origins, _ = cam.pixel_rays(H, W, z_start)
        rays = np.arange(H * W)
    first = scene.intersects_first(origins, np.broadcast_to(RAY_DIRECTION, origins.shape))
    local = np.flatnonzero(first >= 0)
    idx, tri = rays[local], first[local]  # hit pixels (flat, ascending) and their triangles
    hit_flat = np.zeros(H * W, dtype=bool)
    hit_flat[idx] = True

    xy = origins[local, :2]
    bary = _barycentric(scene, tri, xy)
    z = np.einsum("mk,mk->m", bary, scene._corner_z[tri])

    fn = scene.face_normals[tri]
    cn = scene._corner_normals[tri]  # (M, 3, 3)
    vn = bary[:, 0:1] * cn[:, 0] + bary[:, 1:2] * cn[:, 1] + bary[:, 2:3] * cn[:, 2]
    vn, vnorm = _unit(vn)
    # Opposing vertex normals can cancel (thin sheets, creases): fall back to the facet normal there.
    degenerate = vnorm < 1e-8
    vn[degenerate] = fn[degenerate]
    # Face the viewer: orient by the facet (one decision per triangle, so no seams inside a triangle);
    # closed, outward-wound meshes are never flipped, open meshes seen from behind are. The smooth normal
    # then joins the facet's side, which also repairs inverted user-supplied vertex normals.
    facing = np.where(fn[:, 2] != 0, fn[:, 2], vn[:, 2])
    fn = fn * np.where(facing < 0, -1.0, 1.0)[:, None]
    vn = vn * np.where((vn * fn).sum(axis=1) < 0, -1.0, 1.0)[:, None]

    n = H * W
    normal = np.zeros((n, 3), dtype=np.float32)
    face_normal = np.zeros((n, 3), dtype=np.float32)
    points = np.zeros((n, 3), dtype=np.float64)
    bary_img = np.zeros((n, 3), dtype=np.float32)
    depth = np.full(n, -np.inf, dtype=np.float32)
    label = np.zeros(n, dtype=np.int32)
    triangle = np.full(n, -1, dtype=np.int64)
    normal[idx] = vn
    face_normal[idx] = fn
    points[idx, :2] = xy
    points[idx, 2] = z
    bary_img[idx] = bary
    depth[idx] = z
    label[idx] = scene.labels[tri]
    triangle[idx] = tri
    return GBuffer(
        hit=hit_flat.reshape(H, W),
        normal=normal.reshape(H, W, 3),
        face_normal=face_normal.reshape(H, W, 3),
        depth=depth.reshape(H, W),
        points=points.reshape(H, W, 3),
        bary=bary_img.reshape(H, W, 3),
        label=label.reshape(H, W),
        triangle=triangle.reshape(H, W),
        cam=cam,
    )


def interpolate_vertex_attribute(scene: Scene, gbuffer: GBuffer, values) -> np.ndarray:
    """Barycentric interpolation of per-vertex ``values (V, C)`` (or ``(V,)``) at every hit pixel -> float32
    ``(H, W, C)`` (or ``(H, W)``), 0 off-mesh. E.g. per-vertex albedo."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape[0] != len(scene.vertices):
        raise UserError(f"values must have one row per vertex ({len(scene.vertices)}), got {values.shape}")
    scalar = values.ndim == 1
    vals = values[:, None] if scalar else values.reshape(len(values), -1)
    H, W = gbuffer.shape
    out = np.zeros((H * W, vals.shape[1]), dtype=np.float32)
    idx = np.flatnonzero(gbuffer.hit.reshape(-1))
    tri = gbuffer.triangle.reshape(-1)[idx]
    bary = gbuffer.bary.reshape(-1, 3)[idx].astype(np.float64)
    out[idx] = np.einsum("mk,mkc->mc", bary, vals[scene.faces[tri]])
    if scalar:
        return out.reshape(H, W)
    return out.reshape(H, W, *values.shape[1:])
