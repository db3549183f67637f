"""Face geometry from mediapipe FaceMesh: landmarks, the tessellated face surface, ``shape``, ``cam``,
and ``normal``/``depth`` rendered through our ray caster.

Layout of ``shape`` (S = 1404): the 468 FaceMesh vertices (iris points dropped) in camera space (x right,
y up, z toward the viewer; mediapipe's z, whose unit is the image width like x, is negated), centred on
their mean and divided by their RMS distance to it, flattened row-major (x0, y0, z0, x1, ...). It carries
pose, identity shape and expression together, unlike DECA's separate parameters.

``cam`` = (s, tx, ty) is the least-squares orthographic camera that projects those vertices onto the
landmarks (docs/architecture.md); since the vertices are the landmarks up to a similarity the residual is
at float precision on square crops and is reported as ``reprojection_px`` (a check of the conventions).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from difareli.render import OrthoCamera, Scene, render_gbuffer

from .align import FaceMeshRunner, landmarks_to_crop
from .loading import BadInput

NUM_VERTICES = 468
SHAPE_DIM = NUM_VERTICES * 3
#: Triangles found as 3-cliques of the tessellation edges that are not faces of the mesh (OFFLINE.md).
SPURIOUS_TRIANGLES = ((49, 64, 129), (279, 294, 358))


@lru_cache(maxsize=1)
def tessellation_triangles() -> np.ndarray:
    """(F, 3) triangles of FACEMESH_TESSELATION: every 3-clique of its edge graph minus the spurious ones."""
    from mediapipe.python.solutions.face_mesh_connections import FACEMESH_TESSELATION

    adj: dict[int, set[int]] = {}
    for a, b in FACEMESH_TESSELATION:
        if a != b:
            adj.setdefault(a, set()).add(b)
            adj.setdefault(b, set()).add(a)
    tris = {tuple(sorted((a, b, c))) for a in adj for b in adj[a] if b > a for c in adj[a] & adj[b] if c > b}
    tris -= {tuple(sorted(t)) for t in SPURIOUS_TRIANGLES}
    faces = np.array(sorted(tris), dtype=np.int64)
    # Cliques come unordered; smooth normals need one consistent winding (a topological property, so any
    # vertex positions do). The global sign is chosen per image by ``orient_toward_viewer``.
    import trimesh

    mesh = trimesh.Trimesh(np.random.default_rng(0).normal(size=(NUM_VERTICES, 3)), faces, process=False)
    trimesh.repair.fix_winding(mesh)
    return np.asarray(mesh.faces, dtype=np.int64)


def orient_toward_viewer(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` or their flipped copy, whichever makes the area-weighted normal point toward +z."""
    v = vertices[faces]
    nz = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])[:, 2].sum()
    return faces if nz >= 0 else faces[:, ::-1].copy()


def camera_space(landmarks: np.ndarray) -> np.ndarray:
    """FaceMesh pixel landmarks (N, 3) -> camera-space points in pixels (x right, y up, z toward the viewer)."""
    lm = np.asarray(landmarks, dtype=np.float64)
    return np.stack([lm[:, 0], -lm[:, 1], -lm[:, 2]], axis=1)


def normalise(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre on the mean and divide by the RMS radius; returns (normalised, mean, radius)."""
    mean = points.mean(0)
    radius = float(np.sqrt(((points - mean) ** 2).sum(1).mean()))
    return (points - mean) / radius, mean, radius


def fit_camera(vertices: np.ndarray, landmarks_xy: np.ndarray, H: int, W: int) -> tuple[OrthoCamera, float]:
    """Least-squares DECA camera with ``project(vertices) ~ landmarks_xy``; returns (cam, mean error in px).

    ``ndc = s * X + s * t`` is linear in ``(s, s tx, s ty)``; x and y share the scale.
    """
    v = np.asarray(vertices, dtype=np.float64)
    uv = np.asarray(landmarks_xy, dtype=np.float64)
    ndc = np.stack([2 * uv[:, 0] / W - 1, 1 - 2 * uv[:, 1] / H], axis=1)
    n = len(v)
    a = np.zeros((2 * n, 3))
    a[:n, 0], a[:n, 1] = v[:, 0], 1.0
    a[n:, 0], a[n:, 2] = v[:, 1], 1.0
    sol = np.linalg.lstsq(a, np.concatenate([ndc[:, 0], ndc[:, 1]]), rcond=None)[0]
    cam = OrthoCamera(float(sol[0]), float(sol[1] / sol[0]), float(sol[2] / sol[0]))
    err = float(np.linalg.norm(cam.project(v, H, W) - uv, axis=1).mean())
    return cam, err


class FaceMeshGeometry:
    """Estimator: FaceMesh on the aligned crop -> landmarks, face surface, shape, cam, normal, depth."""

    provides = ("landmarks", "scene", "gbuffer", "shape", "cam", "normal", "depth")
    requires = ("image",)

    def __init__(self, min_detection_confidence: float = 0.5, max_reprojection_px: float = 1.0):
        self.mesh = FaceMeshRunner(min_detection_confidence)
        self.max_reprojection_px = max_reprojection_px

    def detect(self, image: np.ndarray) -> list[np.ndarray]:
        """FaceMesh landmarks of each face in ``image`` (subclasses may detect differently)."""
        return self.mesh(image)

    def landmarks(self, ctx: dict) -> tuple[np.ndarray, list[str]]:
        """The aligned crop's landmarks and notes; falls back to the detection pass's landmarks."""
        found = self.detect(ctx["image"])
        if found:
            return found[0], []
        if ctx.get("alignment_landmarks") is not None and ctx.get("quad") is not None:
            # FaceMesh missed the aligned crop: the detection pass's landmarks (photo pixels), mapped into the crop.
            return landmarks_to_crop(ctx["alignment_landmarks"], ctx["quad"], ctx["image"].shape[0]), [
                "FaceMesh failed on the aligned crop; used landmarks from the detection pass"]
        raise BadInput("FaceMesh found no face in the aligned crop")

    def __call__(self, ctx: dict, needed: set[str]) -> dict:
        image = ctx["image"]
        H, W = image.shape[:2]
        lm, notes = self.landmarks(ctx)
        verts, _, _ = normalise(camera_space(lm[:NUM_VERTICES]))
        cam, err = fit_camera(verts, lm[:NUM_VERTICES, :2], H, W)
        if not err <= self.max_reprojection_px:
            raise BadInput(f"camera fit failed: mean reprojection error {err:.2f} px")
        out = {"landmarks": lm, "shape": verts.reshape(-1).astype(np.float32), "cam": cam.to_array(),
               "reprojection_px": err, "notes": notes}
        if needed & {"scene", "gbuffer", "normal", "depth"}:
            scene = Scene.from_arrays(verts, orient_toward_viewer(verts, tessellation_triangles()))
            gb = render_gbuffer(scene, cam, H, W)
            out.update(scene=scene, gbuffer=gb, normal=gb.normal.astype(np.float32),
                       depth=np.where(gb.hit, gb.depth, 0.0).astype(np.float32))
        return out
