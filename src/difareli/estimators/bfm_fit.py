"""BFM fit to a photo: the SynthFaces ``shape`` parameterisation (S = 53) estimated from FaceMesh landmarks.

A model trained on SynthFaces reads ``shape`` = ``FaceParams.shape_vector()`` (40 whitened identity, 10
whitened expression coefficients of the BFM of ``synth.face_model``, then yaw, pitch, roll in radians) and
``cam`` = the DECA camera of the *posed BFM model frame*. This estimator produces exactly those for a photo:

1. FaceMesh's 478 landmarks -> the 68 iBUG/dlib points (``FACEMESH_TO_IBUG68``, averaging index pairs).
2. Fit the BFM's own 68 keypoints (``FaceModel.landmarks``, from 3DDFA's ``keypoints_sim``) to them under
   the scaled-orthographic DECA camera, alternating
   - pose: weighted affine least squares ``y ~ M X + T`` projected onto ``s [r1; r2]`` (orthonormal rows);
   - shape: ridge least squares for the 50 whitened coefficients (a N(0, 1) prior: the ridge is
     ``sigma^2``, ``sigma`` the landmark noise in model units, so weak directions stay at the mean face);
   then a joint Gauss-Newton polish of all 56 unknowns (the alternation is slow along pose/shape trade-offs).
   The 17 jaw points are down-weighted: FaceMesh and the BFM put the contour on different vertices of the
   cheek, and under yaw neither is the silhouette. Only x, y are fitted: FaceMesh's z is a regressed
   relative depth of unknown scale, so it only places the surface below (its agreement is reported).
3. ``normal``/``depth`` are rendered from the FaceMesh surface (denser and pixel-aligned, unlike a 68-point
   BFM fit) expressed in the BFM frame: x, y unprojected through the fitted ``cam`` (so ``cam`` renders it
   exactly), z = FaceMesh's depth scaled like x and shifted onto the fitted BFM's landmark depths. ``cam``,
   ``depth`` and the shadow ray-marching of ``targets`` therefore share SynthFaces' units.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from difareli.errors import UserError
from difareli.render import OrthoCamera, Scene, render_gbuffer
from difareli.render.face_model import N_EXP, N_ID, PIVOT, SHAPE_DIM, FaceModel, FaceParams, pose_points

from .align import landmarks_to_crop
from .geometry import NUM_VERTICES, FaceMeshGeometry, orient_toward_viewer, tessellation_triangles
from .loading import BadInput

__all__ = ["FACEMESH_TO_IBUG68", "SHAPE_DIM", "BFMFit", "BFMGeometry", "facemesh_to_68", "fit_bfm",
           "pose_from_rotation"]

#: FaceMesh vertex(es) of each iBUG-68 landmark (0-based iBUG order; pairs are averaged). Correspondences
#: from Peizhi Yan, "Mediapipe_2_Dlib_Landmarks" (github.com/PeizhiYan/Mediapipe_2_Dlib_Landmarks,
#: mediapipe2dlib/mp2dlib.py, 2024); checked on the astronaut photo (tests/estimators/test_bfm_fit.py).
FACEMESH_TO_IBUG68 = (
    (127,), (234,), (93,), (132, 58), (58, 172), (136,), (150,), (176,), (152,),        # jaw 0-8
    (400,), (379,), (365,), (397, 288), (361,), (323,), (454,), (356,),                # jaw 9-16
    (70,), (63,), (105,), (66,), (107,),                                               # right brow 17-21
    (336,), (296,), (334,), (293,), (300,),                                            # left brow 22-26
    (168, 6), (197, 195), (5,), (4,), (75,), (97,), (2,), (326,), (305,),              # nose 27-35
    (33,), (160,), (158,), (133,), (153,), (144,),                                     # right eye 36-41
    (362,), (385,), (387,), (263,), (373,), (380,),                                    # left eye 42-47
    (61,), (39,), (37,), (0,), (267,), (269,), (291,), (321,), (314,), (17,), (84,), (91,),  # outer lips 48-59
    (78,), (82,), (13,), (312,), (308,), (317,), (14,), (87,),                         # inner lips 60-67
)
JAW = np.arange(17)
# Each iBUG point as the mean of two FaceMesh vertices (a single one twice: (x + x) / 2 == x exactly).
_IBUG_A = np.array([ids[0] for ids in FACEMESH_TO_IBUG68])
_IBUG_B = np.array([ids[-1] for ids in FACEMESH_TO_IBUG68])


def facemesh_to_68(landmarks: np.ndarray) -> np.ndarray:
    """(68, D) iBUG-order points from FaceMesh landmarks (468 or 478, D)."""
    lm = np.asarray(landmarks, dtype=np.float64)
    return (lm[_IBUG_A] + lm[_IBUG_B]) / 2  # what the mean of each pair gives, bit for bit


@functools.lru_cache(maxsize=2)
def _landmark_model(model: FaceModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 68 keypoints' part of ``model``, built once per model: float64 mean (68, 3) and bases (68, 3, 50) for
    the fit, and the float32 coefficient-major bases (50, 204) for :func:`posed_landmarks` (the full model is
    ~10k vertices; a fit only ever needs these 68)."""
    rows = (3 * model.landmarks[:, None] + np.arange(3)).ravel()
    basis = np.c_[model.id_basis, model.exp_basis][rows]  # (204, 50) float32
    return (model.mean[model.landmarks].astype(np.float64), basis.astype(np.float64).reshape(-1, 3, N_ID + N_EXP),
            np.ascontiguousarray(basis.T))


def posed_landmarks(model: FaceModel, params: FaceParams) -> np.ndarray:
    """``model.build(params)[0][model.landmarks]`` (68, 3) float32 without building the other vertices (equal to
    float32 rounding: the same float32 sums over the 68 keypoints' columns only)."""
    coeffs = np.r_[params.identity, params.expression].astype(np.float32)
    v = model.mean[model.landmarks] + np.einsum("i,ij->j", coeffs, _landmark_model(model)[2]).reshape(-1, 3)
    return pose_points(v, params.pose)


def pose_from_rotation(r: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) degrees of ``R = Ry(yaw) @ Rx(pitch) @ Rz(roll)`` (inverse of ``rotation_matrix``)."""
    yaw = np.arctan2(r[0, 2], r[2, 2])
    pitch = np.arcsin(np.clip(-r[1, 2], -1.0, 1.0))
    roll = np.arctan2(r[1, 0], r[1, 1])
    return np.degrees([yaw, pitch, roll])


def _rodrigues(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3)
    k = w / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx


@dataclass(frozen=True)
class BFMFit:
    """A fitted face: SynthFaces parameters, DECA camera, and the 68 keypoints' reprojection."""

    params: FaceParams
    cam: OrthoCamera
    projected: np.ndarray  # (68, 2) pixels
    rmse_px: float  # over all 68 points, unweighted
    rmse_inner_px: float  # the 51 non-jaw points

    def landmarks3d(self, model: FaceModel | None = None) -> np.ndarray:
        """Posed BFM 68 keypoints (68, 3) in the model frame."""
        return posed_landmarks(model or FaceModel.load(), self.params).astype(np.float64)


def _pose_step(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted scaled-orthographic pose ``y ~ s R[:2] x + T``: (s, R 3x3, T)."""
    ww = w / w.sum()
    xm, ym = ww @ x, ww @ y
    xc, yc = x - xm, y - ym
    m = np.linalg.solve((xc * ww[:, None]).T @ xc, (xc * ww[:, None]).T @ yc).T  # (2, 3) affine
    u, sv, vt = np.linalg.svd(m, full_matrices=False)
    r2 = u @ vt  # nearest matrix with orthonormal rows
    s = float(np.sum(ww[:, None] * (xc @ r2.T) * yc) / np.sum(ww[:, None] * (xc @ r2.T) ** 2))
    r = np.vstack([r2, np.cross(r2[0], r2[1])])
    return s, r, ym - s * xm @ r2.T


def fit_bfm(landmarks_xy: np.ndarray, H: int, W: int, *, model: FaceModel | None = None, jaw_weight: float = 0.25,
            sigma: float = 0.01, iterations: int = 8, polish: int = 10) -> BFMFit:
    """Fit BFM identity/expression, pose and the DECA camera to 68 iBUG points in pixels (see module doc).

    ``sigma``: landmark noise in model units (the face is ~1 wide, so 0.01 ~ 1.5 px on a 256 FFHQ crop); the
    ridge weight on the whitened coefficients is ``sigma^2`` per unit-weight point.
    """
    model = model or FaceModel.load()
    uv = np.asarray(landmarks_xy, dtype=np.float64)
    y = np.stack([2 * uv[:, 0] / W - 1, 1 - 2 * uv[:, 1] / H], axis=1)  # NDC
    mean, basis, _ = _landmark_model(model)
    n_c = N_ID + N_EXP
    # (3, 68 * 50): ``r[:2] @ b3`` is every keypoint's basis rotated, one BLAS product (an einsum took 5x longer).
    b3 = basis.transpose(1, 0, 2).reshape(3, -1)

    def rotated_basis(r_):  # (136, 50): rows x0, y0, x1, ... of R[:2] times each keypoint's basis
        return (r_[:2] @ b3).reshape(2, 68, n_c).transpose(1, 0, 2).reshape(-1, n_c)

    w = np.ones(68)
    w[JAW] = jaw_weight
    sw = np.repeat(w, 2)
    ridge = sigma ** 2 * np.eye(n_c)
    c = np.zeros(n_c)
    for _ in range(iterations):
        s, r, t = _pose_step(mean + basis @ c, y, w)
        # Shape: residual in model units (divided by s) so that sigma does not depend on the crop size.
        a = rotated_basis(r)
        b = ((y - t) / s - mean @ r[:2].T).reshape(-1)
        c = np.linalg.solve(a.T @ (a * sw[:, None]) + ridge, a.T @ (sw * b))
    # Joint Gauss-Newton (Levenberg-damped) on (rotation increment, log s, T, c): the same objective.
    # Residuals are divided by the initial scale s0 (fixed, so shrinking s cannot lower the data term).
    sqw, s0 = np.sqrt(sw), s

    def residual(r_, s_, t_, c_):
        proj = s_ * (mean + basis @ c_) @ r_[:2].T + t_
        return np.r_[sqw * ((proj - y) / s0).reshape(-1), sigma * c_]

    lam = 1e-3
    cur = residual(r, s, t, c)
    jac = np.zeros((136 + n_c, 6 + n_c))
    jac[136:, 6:] = sigma * np.eye(n_c)
    row_w = (sqw / s0)[:, None]
    jac[:136, 4:6] = np.tile(np.eye(2), (68, 1)) * row_w  # d/dT: constant
    for _ in range(polish):
        xr = (mean + basis @ c) @ r.T  # rotated keypoints (68, 3)
        # d/dw_k of s (R_delta R x)_xy with R_delta = I + [w]x: the xy of e_k x xr, written out.
        zero = np.zeros(68)
        jac[:136, 0] = np.stack([zero, -xr[:, 2]], 1).reshape(-1)
        jac[:136, 1] = np.stack([xr[:, 2], zero], 1).reshape(-1)
        jac[:136, 2] = np.stack([-xr[:, 1], xr[:, 0]], 1).reshape(-1)
        jac[:136, 3] = xr[:, :2].reshape(-1)
        jac[:136, :4] *= s
        jac[:136, 6:] = s * rotated_basis(r)
        jac[:136, :4] *= row_w
        jac[:136, 6:] *= row_w
        g = jac.T @ cur
        h = jac.T @ jac
        step = np.linalg.solve(h + lam * np.diag(np.diag(h) + 1e-12), -g)
        r_new = _rodrigues(step[:3]) @ r
        s_new, t_new, c_new = s * np.exp(step[3]), t + step[4:6], c + step[6:]
        new = residual(r_new, s_new, t_new, c_new)
        if new @ new < cur @ cur:
            r, s, t, c, cur, lam = r_new, s_new, t_new, c_new, new, lam / 3
            if np.abs(step).max() < 1e-9:
                break
        else:
            lam *= 10
    params = FaceParams(c[:N_ID].copy(), c[N_ID:].copy(), pose_from_rotation(r))
    # y = s R x + T with the pose applied about PIVOT: s (R (x - p) + p + t)_xy = s R x + T.
    cam = OrthoCamera(s, *(t / s + (r @ PIVOT)[:2] - PIVOT[:2]))
    proj = cam.project(posed_landmarks(model, params), H, W)
    err = np.linalg.norm(proj - uv, axis=1)
    return BFMFit(params, cam, proj, float(np.sqrt((err ** 2).mean())), float(np.sqrt((err[17:] ** 2).mean())))


class BFMGeometry(FaceMeshGeometry):
    """Estimator: FaceMesh landmarks -> BFM fit (``shape`` S = 53, ``cam`` in the BFM frame, as SynthFaces);
    ``normal``/``depth`` from the FaceMesh surface placed in that frame (module doc)."""

    provides = ("landmarks", "scene", "gbuffer", "shape", "cam", "normal", "depth", "bfm_fit")
    requires = ("image",)
    shape_dim = SHAPE_DIM

    def __init__(self, min_detection_confidence: float = 0.5, jaw_weight: float = 0.25, sigma: float = 0.01,
                 iterations: int = 8, polish: int = 10, max_rmse: float = 0.03, mesh_min_size: int = 192,
                 landmark_source: str = "crop"):
        super().__init__(min_detection_confidence)
        self.fit_options = dict(jaw_weight=jaw_weight, sigma=sigma, iterations=iterations, polish=polish)
        self.max_rmse = max_rmse
        self.mesh_min_size = mesh_min_size
        if landmark_source not in ("crop", "alignment"):
            raise UserError(f"landmark_source must be 'crop' or 'alignment', got {landmark_source!r}")
        self.landmark_source = landmark_source

    def landmarks(self, ctx: dict) -> tuple[np.ndarray, list[str]]:
        """``landmark_source="crop"``: FaceMesh on the aligned crop (:meth:`FaceMeshGeometry.landmarks`).
        ``"alignment"``: the alignment pass's landmarks mapped into the crop, which saves that second FaceMesh
        pass (~5 ms per image) but moves them: by a mean 0.4-0.8 px at 256 px on the astronaut and Grace Hopper
        (about what a 0.35 px shift of the crop does to the second pass), 1.5 px on the cameraman (yaw 50 deg) and
        5 px on his mirror image (tests/estimators/test_preprocess_speed.py); hence not the default."""
        if self.landmark_source == "alignment" and ctx.get("alignment_landmarks") is not None:
            return landmarks_to_crop(ctx["alignment_landmarks"], ctx["quad"], ctx["image"].shape[0]), []
        return super().landmarks(ctx)

    def detect(self, image: np.ndarray) -> list[np.ndarray]:
        """FaceMesh landmarks (478, 3) in ``image`` pixels; small crops are upsampled first (FaceMesh misses
        faces much below ~128 px)."""
        H, W = image.shape[:2]
        f = max(1.0, self.mesh_min_size / min(H, W))
        if f == 1.0:
            return self.mesh(image)
        import cv2

        big = cv2.resize(image, (round(W * f), round(H * f)), interpolation=cv2.INTER_CUBIC)
        fx, fy = big.shape[1] / W, big.shape[0] / H
        return [lm / [fx, fy, fx] for lm in self.mesh(big)]

    def __call__(self, ctx: dict, needed: set[str]) -> dict:
        image = ctx["image"]
        H, W = image.shape[:2]
        lm, notes = self.landmarks(ctx)
        fit = fit_bfm(facemesh_to_68(lm[:, :2]), H, W, **self.fit_options)
        if not fit.rmse_px <= self.max_rmse * max(H, W):
            raise BadInput(f"BFM fit failed: landmark RMSE {fit.rmse_px:.2f} px")
        model = FaceModel.load()
        # FaceMesh surface in the BFM frame: x, y through the fitted camera, z scaled like x (mediapipe's
        # convention) and shifted so its 51 inner landmarks have the fitted BFM's mean depth.
        verts = fit.cam.unproject(lm[:NUM_VERTICES, :2], 0.0, H, W)
        z = -lm[:NUM_VERTICES, 2] * 2.0 / (W * fit.cam.scale)
        bfm_z = fit.landmarks3d(model)[17:, 2]
        mesh_z = facemesh_to_68(z[:, None])[17:, 0]
        verts[:, 2] = z + (bfm_z - mesh_z).mean()
        z_corr = float(np.corrcoef(bfm_z, mesh_z)[0, 1])
        info = {"rmse_px": round(fit.rmse_px, 3), "rmse_inner_px": round(fit.rmse_inner_px, 3),
                "pose_deg": np.round(fit.params.pose, 2).tolist(), "z_corr": round(z_corr, 3)}
        out = {"landmarks": lm, "shape": fit.params.shape_vector(), "cam": fit.cam.to_array(),
               "reprojection_px": fit.rmse_px, "bfm_fit": info, "notes": notes}
        if needed & {"scene", "gbuffer", "normal", "depth"}:
            scene = Scene.from_arrays(verts, orient_toward_viewer(verts, tessellation_triangles()))
            gb = render_gbuffer(scene, fit.cam, H, W)
            out.update(scene=scene, gbuffer=gb, normal=gb.normal.astype(np.float32),
                       depth=np.where(gb.hit, gb.depth, 0.0).astype(np.float32))
        return out
