"""Non-facial geometry of SynthFaces (skull, hair cap, neck, shoulders, hat) and the full head: ``build_head``.

All parts live in the face model's camera space (``face_model``: x right, y up, z toward the viewer, head
~unit scale, origin near the middle of the head) and carry ``MASK_PARTS`` labels per triangle:
- skull (``skin``): an egg-shaped ellipsoid closing the back and sides of the cropped BFM face; its front is
  pushed behind the face surface so it never pokes through, and it is always closed, so rays cannot leak.
- hair cap (``hair``): the same ellipsoid inflated by a random volume, kept above a hairline that runs from
  the forehead (random height) down to the back (random length); over the forehead it is lifted in front of
  the face. A single-sided shell; the skull lies under it. ``bald`` heads have none.
- neck (``neck``): a vertical cylinder around the pose pivot's vertical axis (``face_model.PIVOT``); its
  top hides inside the skull. Shoulders/clothes (``clothes``): a flattened ellipsoid below the neck.
- hat (``hat``, optional): an elliptic crown cylinder with a top and a brim (a thin closed disc ring) that
  casts a shadow on the face under a top light.

Posing: the face, skull, hair and hat rotate rigidly with the head pose about ``PIVOT`` (top of the neck);
the neck and shoulders do not rotate (the neck is coaxial with the yaw axis, so the seam under the chin stays
closed for yaw, and pitch/roll of <= 15 degrees keep the neck top inside the skull).
Skull and hair follow the subject's identity/expression through the displacement of their nearest face
vertices (inverse-distance weights fixed on the mean face).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from difareli.data.encodings import PART_INDEX
from difareli.errors import UserError
from difareli.render.face_model import PIVOT, FaceModel, FaceParams, pose_points

SKULL_CENTRE = np.array([0.0, 0.05, 0.0])
SKULL_RADII = np.array([0.52, 0.75, 0.68, 0.6, 0.9])  # x, y top, z front, z back, y bottom
_BEHIND_FACE = 0.05  # skull kept this far behind the mean face (identity variation stays in front of it)
_HAIR_LIFT = 0.025  # hair over the forehead floats this far in front of the face


@dataclass(frozen=True)
class AccessoryParams:
    """Random style of the non-facial parts (all lengths in model units)."""

    bald: bool = False
    hairline: float = 0.6  # elevation (unit-sphere y) of the hairline at the forehead
    hair_back: float = 0.3  # how far below the equator (unit-sphere y) the hair reaches at the back
    hair_volume: float = 0.08  # inflation of the hair ellipsoid over the skull
    neck_radius: float = 0.37
    shoulder_width: float = 1.35
    shoulder_height: float = 0.5
    shoulder_top: float = -1.2
    hat: bool = False
    hat_base: float = 0.42  # crown bottom / brim height above the skull centre (head frame)
    hat_height: float = 0.5
    brim_width: float = 0.35


def sample_accessories(rng: np.random.Generator, *, hat_prob: float = 0.2, bald_prob: float = 0.05) -> AccessoryParams:
    """Random accessory style."""
    u = rng.uniform(size=12)
    return AccessoryParams(
        bald=bool(u[0] < bald_prob),
        hairline=0.4 + 0.3 * u[1],
        hair_back=-0.1 + 0.8 * u[2],
        hair_volume=0.04 + 0.1 * u[3],
        neck_radius=0.34 + 0.06 * u[4],
        shoulder_width=1.2 + 0.35 * u[5],
        shoulder_height=0.42 + 0.18 * u[6],
        shoulder_top=-1.25 + 0.1 * u[7],
        hat=bool(u[8] < hat_prob),
        hat_base=0.38 + 0.12 * u[9],
        hat_height=0.35 + 0.3 * u[10],
        brim_width=0.2 + 0.4 * u[11],
    )


_SPHERE_RES = (32, 64)  # skull sphere grid (rings, azimuths); the hair cap reuses its azimuths


@functools.lru_cache(maxsize=8)
def _sphere(n_lat: int = _SPHERE_RES[0], n_lon: int = _SPHERE_RES[1]) -> tuple[np.ndarray, np.ndarray]:
    """Closed unit UV sphere (outward winding): vertices (poles first/last) and faces."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(-np.pi, np.pi, n_lon, endpoint=False)
    t, p = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], -1).reshape(-1, 3)
    v = np.r_[[[0, 1, 0]], ring, [[0, -1, 0]]]
    f = []
    idx = lambda i, j: 1 + i * n_lon + (j % n_lon)  # noqa: E731
    for j in range(n_lon):
        f.append([0, idx(0, j + 1), idx(0, j)])
        f.append([len(v) - 1, idx(n_lat - 2, j), idx(n_lat - 2, j + 1)])
        for i in range(n_lat - 2):
            a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
            f += [[a, b, d], [a, d, c]]
    return v, np.asarray(f, np.int64)


@functools.lru_cache(maxsize=8)
def _cylinder(n_around: int = 48, caps: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Unit cylinder around +y from y=0 to y=1 (outward winding), optionally with end caps."""
    a = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    ring = np.c_[np.sin(a), np.zeros(n_around), np.cos(a)]
    v = np.r_[ring, ring + [0, 1, 0]]
    j = np.arange(n_around)
    k = (j + 1) % n_around
    f = np.r_[np.c_[j, k, k + n_around], np.c_[j, k + n_around, j + n_around]]
    if caps:
        v = np.r_[v, [[0, 0, 0], [0, 1, 0]]]
        b, t = 2 * n_around, 2 * n_around + 1
        f = np.r_[f, np.c_[np.full(n_around, b), k, j], np.c_[np.full(n_around, t), j + n_around, k + n_around]]
    return v, f


def _ellipsoid(d: np.ndarray, centre: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Points of an egg ellipsoid (radii x, y top, z front, z back, y bottom) along unit directions ``d``.

    The deeper bottom reaches into the neck so the jaw corners are backed by the skull.
    """
    rz = np.where(d[:, 2] > 0, radii[2], radii[3])
    ry = np.where(d[:, 1] > 0, radii[1], radii[4])
    return centre + d * np.c_[np.full(len(d), radii[0]), ry, rz]


class _Template:
    """Per-process precomputation shared by every head: front height field, skull, attachment weights."""

    def __init__(self, model: FaceModel):
        self.model = model
        d, self.sphere_faces = _sphere()
        self.dirs = d
        mesh = trimesh.Trimesh(model.mean, model.faces, process=False)
        base = _ellipsoid(d, SKULL_CENTRE, SKULL_RADII)
        self.skull = base.copy()
        zf = self.front_z(mesh, base[:, :2])
        push = np.isfinite(zf) & (base[:, 2] > zf - _BEHIND_FACE)
        self.skull[push, 2] = zf[push] - _BEHIND_FACE
        # Hair is lifted over the face along the unit-sphere grid; which grid points lie in front of the face is
        # decided per subject from this field sampled at the hair's own xy.
        self.mesh = mesh
        dist, nn = cKDTree(model.mean).query(base, k=8)
        w = 1.0 / np.maximum(dist, 1e-3) ** 2
        self.nn, self.w = nn, (w / w.sum(1, keepdims=True)).astype(np.float32)
        # Height field of the mean face on a grid, for fast per-subject hair lifting.
        lo, hi = model.mean[:, :2].min(0) - 0.02, model.mean[:, :2].max(0) + 0.02
        self.grid_lo, self.grid_step = lo, (hi - lo) / 127
        gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 128), np.linspace(lo[1], hi[1], 128), indexing="ij")
        self.grid_z = self.front_z(mesh, np.c_[gx.ravel(), gy.ravel()]).reshape(128, 128)

    @staticmethod
    def front_z(mesh: trimesh.Trimesh, xy: np.ndarray) -> np.ndarray:
        """Largest z of ``mesh`` above each xy (-inf where no surface)."""
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        o = np.c_[xy, np.full(len(xy), 10.0)]
        down = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
        _, ray, loc = RayMeshIntersector(mesh).intersects_id(o, down, multiple_hits=False, return_locations=True)
        z = np.full(len(xy), -np.inf)
        z[ray] = loc[:, 2]
        return z

    def grid_front_z(self, xy: np.ndarray) -> np.ndarray:
        """Nearest-cell lookup of the mean face's front z (-inf off the face)."""
        ij = np.rint((xy - self.grid_lo) / self.grid_step).astype(np.int64)
        ok = (ij >= 0).all(1) & (ij < 128).all(1)
        z = np.full(len(xy), -np.inf)
        z[ok] = self.grid_z[ij[ok, 0], ij[ok, 1]]
        return z

    def follow(self, disp: np.ndarray) -> np.ndarray:
        """Displacement of the sphere-grid points given the face vertices' displacement (V, 3)."""
        return np.einsum("nk,nkc->nc", self.w, disp[self.nn])


@functools.lru_cache(maxsize=1)
def _template() -> _Template:
    return _Template(FaceModel.load())


@dataclass
class HeadGeometry:
    """A posed synthetic head: one triangle mesh with a ``MASK_PARTS`` label per triangle."""

    vertices: np.ndarray  # (V, 3) float32, camera space
    faces: np.ndarray  # (F, 3) int32
    face_labels: np.ndarray  # (F,) uint8, MASK_PARTS indices
    shape_vector: np.ndarray  # (S,) float32, FaceParams.shape_vector()
    params: FaceParams
    accessories: AccessoryParams
    landmarks: np.ndarray  # (68, 3) float32 posed iBUG landmarks
    n_face_faces: int = 0  # the first n_face_faces triangles are the BFM face (the shading-reference mesh)
    parts: dict[str, slice] = field(default_factory=dict)  # component name -> triangle slice

    @property
    def mesh(self) -> trimesh.Trimesh:
        """The geometry as an unprocessed ``trimesh.Trimesh`` (triangle order kept)."""
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def _hair(t: _Template, a: AccessoryParams, disp: np.ndarray, n_rows: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Hair cap: a grid from the crown down to the hairline, so its edge follows the hairline exactly."""
    n_lat, n_lon = _SPHERE_RES
    phi = np.linspace(-np.pi, np.pi, n_lon, endpoint=False)
    # Hairline (unit-sphere y): `hairline` at the forehead (azimuth 0) down to -hair_back at the back (azimuth pi).
    thr = a.hairline + (-a.hair_back - a.hairline) * (np.abs(phi) / np.pi) ** 1.5
    theta = np.arccos(np.clip(thr, -0.98, 0.98))[None, :] * (np.arange(1, n_rows + 1)[:, None] / n_rows)
    ph = np.broadcast_to(phi, theta.shape)
    rows = np.stack([np.sin(theta) * np.sin(ph), np.cos(theta), np.sin(theta) * np.cos(ph)], -1).reshape(-1, 3)
    d = np.r_[[[0.0, 1.0, 0.0]], rows]
    # Follow the face like the nearest point of the skull's sphere grid (same azimuths, rings at pi / n_lat).
    ring = np.clip(np.rint(theta / (np.pi / n_lat)).astype(np.int64) - 1, 0, n_lat - 2)
    near = np.r_[0, (1 + ring * n_lon + np.arange(n_lon)[None, :]).ravel()]
    dd = disp[near]
    vol = a.hair_volume  # hair is thinner on the crown and the forehead than at the sides and back
    radii = SKULL_RADII * np.array([1 + vol, 1 + 0.7 * vol, 1 + 0.5 * vol, 1 + vol, 1])
    v = _ellipsoid(d, SKULL_CENTRE + [0, 0.02, -0.02], radii) + dd
    front = d[:, 2] > 0  # only the front half can be over the face (the back shares its xy)
    zf = t.grid_front_z(v[front, :2]) + dd[front, 2] + _HAIR_LIFT
    v[front, 2] = np.maximum(v[front, 2], zf)
    idx = lambda r, c: 1 + r * n_lon + (c % n_lon)  # noqa: E731
    c = np.arange(n_lon)
    f = [np.c_[np.zeros(n_lon, np.int64), idx(0, c + 1), idx(0, c)]]
    for r in range(n_rows - 1):
        f += [np.c_[idx(r, c), idx(r, c + 1), idx(r + 1, c + 1)], np.c_[idx(r, c), idx(r + 1, c + 1), idx(r + 1, c)]]
    return v, np.concatenate(f)


def _hat(a: AccessoryParams, hair_radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Crown (closed elliptic cylinder) and brim (thin closed ring) in the unposed head frame."""
    rx, rz = hair_radii[0] + 0.04, max(hair_radii[2], hair_radii[3]) + 0.04
    cv, cf = _cylinder()
    base = SKULL_CENTRE[1] + a.hat_base
    crown = cv * [rx, a.hat_height, rz] + [0, base, SKULL_CENTRE[2]]
    # Brim: outer and inner rings at two heights, stitched into a closed annulus.
    n = len(_cylinder(caps=False)[0]) // 2
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    unit = np.c_[np.sin(ang), np.zeros(n), np.cos(ang)]
    inner, outer = unit * [rx, 0, rz], unit * [rx + a.brim_width, 0, rz + a.brim_width]
    th = 0.02
    rings = np.r_[inner + [0, base, 0], outer + [0, base, 0], outer + [0, base + th, 0], inner + [0, base + th, 0]]
    rings[:, 2] += SKULL_CENTRE[2]
    j = np.arange(n)
    k = (j + 1) % n
    bf = []
    for r in range(4):  # ring r -> ring r+1 (cyclic): bottom, outer rim, top, inner rim
        s, e = r * n, ((r + 1) % 4) * n
        bf += [np.c_[s + j, e + k, s + k], np.c_[s + j, e + j, e + k]]
    return np.r_[crown, rings], np.r_[cf, np.concatenate(bf) + len(crown)]


def build_head(params: FaceParams | None = None, accessories: AccessoryParams | None = None,
               rng: np.random.Generator | None = None) -> HeadGeometry:
    """Full posed head: face + skull + hair + neck + shoulders (+ hat). Missing params are drawn from ``rng``."""
    t = _template()
    model = t.model
    if params is None or accessories is None:
        if rng is None:
            raise UserError("build_head needs an rng when params or accessories are not given")
        params = params if params is not None else model.sample_params(rng)
        accessories = accessories if accessories is not None else sample_accessories(rng)
    a = accessories
    face_v = model.shape(params)
    disp = t.follow(face_v - model.mean)
    head_parts: list[tuple[str, np.ndarray, np.ndarray, int]] = [
        ("face", face_v, model.faces, -1),
        ("skull", t.skull + disp, t.sphere_faces, PART_INDEX["skin"]),
    ]
    if not a.bald:
        hv, hf = _hair(t, a, disp)
        head_parts.append(("hair", hv, hf, PART_INDEX["hair"]))
    if a.hat:
        hair_radii = SKULL_RADII * (1 + (0 if a.bald else a.hair_volume))
        hv, hf = _hat(a, hair_radii)
        head_parts.append(("hat", hv, hf, PART_INDEX["hat"]))
    cv, cf = _cylinder(caps=False)
    neck_top = PIVOT[1] + 0.3
    neck_bottom = a.shoulder_top - 0.3
    neck = cv * [a.neck_radius, neck_top - neck_bottom, a.neck_radius] + [PIVOT[0], neck_bottom, PIVOT[2]]
    sv, sf = _sphere(16, 48)
    body = sv * [a.shoulder_width, a.shoulder_height, 0.55] + [0, a.shoulder_top - a.shoulder_height, PIVOT[2] - 0.05]
    body_parts = [("neck", neck, cf, PART_INDEX["neck"]), ("clothes", body, sf, PART_INDEX["clothes"])]

    verts, faces, labels, parts = [], [], [], {}
    nv = nf = 0
    for i, (name, v, f, lab) in enumerate(head_parts + body_parts):
        if i < len(head_parts):
            v = pose_points(v, params.pose)
        verts.append(np.asarray(v, np.float32))
        faces.append(np.asarray(f, np.int64) + nv)
        labels.append(model.face_labels if lab < 0 else np.full(len(f), lab, np.uint8))
        parts[name] = slice(nf, nf + len(f))
        nv += len(v)
        nf += len(f)
    v_all = np.concatenate(verts)
    return HeadGeometry(
        vertices=v_all, faces=np.concatenate(faces).astype(np.int32), face_labels=np.concatenate(labels),
        shape_vector=params.shape_vector(), params=params, accessories=a,
        landmarks=v_all[model.landmarks].copy(), n_face_faces=len(model.faces), parts=parts,
    )


def default_camera(head: HeadGeometry | FaceParams, zoom: float = 1.0) -> np.ndarray:
    """DECA camera ``(s, tx, ty)`` framing the head like an FFHQ crop (float32).

    FFHQ's alignment rule on the posed landmarks: centre ``c = eye_avg + 0.1 * eye_to_mouth``, half-size
    ``max(2 |eye_to_eye|, 1.8 |eye_to_mouth|)`` (its in-plane rotation is dropped: the camera has none), so
    ``s = zoom / half_size`` and ``t = -c``. ``zoom < 1`` shows more of the shoulders.
    """
    if isinstance(head, FaceParams):
        v, _ = FaceModel.load().build(head)
        lm = v[FaceModel.load().landmarks]
    else:
        lm = head.landmarks
    xy = lm[:, :2].astype(np.float64)
    eye_l, eye_r = xy[42:48].mean(0), xy[36:42].mean(0)
    eye_avg, eye_to_eye = (eye_l + eye_r) / 2, eye_l - eye_r
    mouth_avg = (xy[48] + xy[54]) / 2
    eye_to_mouth = mouth_avg - eye_avg
    half = max(2.0 * np.linalg.norm(eye_to_eye), 1.8 * np.linalg.norm(eye_to_mouth))
    c = eye_avg + 0.1 * eye_to_mouth
    return np.array([zoom / half, -c[0], -c[1]], np.float32)
