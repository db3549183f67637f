"""Second-order spherical-harmonics lighting in DECA's convention (SPEC 3).

``E(n) = sum_k l_k c_k H_k(n)`` with the basis ``H = [1, x, y, z, xy, xz, yz, x^2-y^2, 3z^2-1]`` and the
constants ``c_k`` below, which fold the Lambertian convolution into bands 1 and 2 (DECA leaves band 0
without the factor pi: see docs/architecture.md). ``sh_basis``, ``irradiance``, ``shading_reference`` and
``rotate`` accept numpy arrays or torch tensors and return the same kind; the other helpers (directional
lights, rotation matrices, dominant direction, env maps, fitting) accept either, compute in float64 numpy
and return numpy.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from difareli.errors import UserError

#: c_k of SPEC 3, exact values.
SH_CONSTANTS = np.array(
    [1 / math.sqrt(4 * math.pi)]
    + [(2 * math.pi / 3) * math.sqrt(3 / (4 * math.pi))] * 3
    + [(math.pi / 4) * 3 * math.sqrt(5 / (12 * math.pi))] * 3
    + [(math.pi / 4) * (3 / 2) * math.sqrt(5 / (12 * math.pi)), (math.pi / 4) * (1 / 2) * math.sqrt(5 / (4 * math.pi))],
    dtype=np.float64,
)

#: Albedo of the shading reference (SPEC 3).
SHADING_ALBEDO = 0.7


def _stack(xs, like):
    return torch.stack(xs, dim=-1) if isinstance(like, torch.Tensor) else np.stack(xs, axis=-1)


def sh_basis(normals):
    """Scaled basis ``c_k H_k(n)`` of unit normals ``(..., 3)`` -> ``(..., 9)``."""
    x, y, z = normals[..., 0], normals[..., 1], normals[..., 2]
    one = x * 0 + 1
    h = _stack([one, x, y, z, x * y, x * z, y * z, x * x - y * y, 3 * z * z - 1], normals)
    if isinstance(h, torch.Tensor):
        return h * torch.as_tensor(SH_CONSTANTS, dtype=h.dtype, device=h.device)
    return h * SH_CONSTANTS.astype(h.dtype if np.issubdtype(h.dtype, np.floating) else np.float64)


def irradiance(light, normals):
    """Irradiance ``(..., 3)`` of SH ``light`` (9x3, or Bx9x3 with normals Bx...x3) on unit ``normals``."""
    basis = sh_basis(normals)  # (..., 9)
    if isinstance(basis, torch.Tensor):
        light = torch.as_tensor(light, dtype=basis.dtype, device=basis.device)
    else:
        light = np.asarray(light, dtype=basis.dtype)
    if light.ndim == 2:
        return basis @ light
    # Batched lights: broadcast (B, 9, 3) over (B, ..., 9).
    lead = basis.shape[0]
    flat = basis.reshape(lead, -1, 9)
    out = flat @ light
    return out.reshape(*basis.shape[:-1], 3)


def shading_reference(light, normals, mask=None, albedo: float = SHADING_ALBEDO):
    """Shading reference ``R = albedo * irradiance`` (SPEC 3), unclipped; 0 where ``mask`` is False."""
    r = albedo * irradiance(light, normals)
    if mask is not None:
        r = r * mask[..., None]
    return r


# ---------------------------------------------------------------------------------------------------------
# Radiance <-> DECA lighting. ``c_k H_k = A_l Y_k`` with Y the orthonormal real SH and the per-band factor
# A = (1, 2pi/3, pi/4): DECA drops pi from band 0, so the radiance coefficients are L_0 = l_0 / pi, L_k = l_k.
_BAND = np.array([0, 1, 1, 1, 2, 2, 2, 2, 2])
_BAND_FACTOR = np.array([1.0, 2 * math.pi / 3, math.pi / 4])[_BAND]
_LIGHT_FROM_RADIANCE = np.array([math.pi] + [1.0] * 8)


def _f64(a) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    return np.asarray(a, dtype=np.float64)


def real_sh(directions) -> np.ndarray:
    """Orthonormal real SH ``Y_k`` of unit ``directions`` ``(..., 3)`` -> ``(..., 9)``, DECA order."""
    return sh_basis(_f64(directions)) / _BAND_FACTOR


def light_from_radiance(coeffs) -> np.ndarray:
    """DECA ``light`` ``(..., 9, 3)`` from the real-SH coefficients ``L`` of a radiance (``l_0 = pi L_0``)."""
    return _f64(coeffs) * _LIGHT_FROM_RADIANCE[:, None]


def radiance_from_light(light) -> np.ndarray:
    """Real-SH radiance coefficients ``L`` ``(..., 9, 3)`` of a DECA ``light`` (inverse of the above)."""
    return _f64(light) / _LIGHT_FROM_RADIANCE[:, None]


def directional_light(direction, intensity=1.0) -> np.ndarray:
    """SH ``light`` (9x3) of a delta radiance of RGB ``intensity`` arriving from unit ``direction``.

    ``irradiance(directional_light(d, I), n)`` is the 9-term approximation of ``I * max(0, n.d)``;
    at ``n = d`` it equals ``(1/4 + 1/2 + 5/16) I = 1.0625 I``. ``direction`` is normalised here.
    """
    d = _f64(direction)
    norm = np.linalg.norm(d)
    if d.shape != (3,) or not norm > 0:
        raise UserError(f"direction must be a non-zero 3-vector, got {d!r}")
    rgb = np.broadcast_to(_f64(intensity), (3,))
    return light_from_radiance(real_sh(d / norm)[:, None] * rgb[None, :])


# ---------------------------------------------------------------------------------------------------------
# Rotations. M(R) is defined by Y(R w) = M(R) Y(w); it is block-diagonal and orthogonal, and because the
# DECA scaling is constant within a band the same M acts on ``light``. Rotating the environment by R
# (new radiance L'(w) = L(R^T w)) maps its coefficients to M(R) L, so E'(R n) = E(n).


def _band2_forms() -> np.ndarray:
    """Symmetric traceless Q_k with Y_k(n) = n^T Q_k n for the five band-2 functions (unit n)."""
    q = np.zeros((5, 3, 3))
    q[0, 0, 1] = q[0, 1, 0] = 0.5  # xy
    q[1, 0, 2] = q[1, 2, 0] = 0.5  # xz
    q[2, 1, 2] = q[2, 2, 1] = 0.5  # yz
    q[3] = np.diag([1.0, -1.0, 0.0])  # x^2 - y^2
    q[4] = np.diag([-1.0, -1.0, 2.0])  # 3z^2 - 1 = 3z^2 - |n|^2 on the sphere, made traceless
    scale = SH_CONSTANTS[4:] / _BAND_FACTOR[4:]
    return q * scale[:, None, None]


_Q2 = _band2_forms()
# Both R^T Q_k R and Q_j are traceless symmetric, so the 5x5 block is an exact linear solve in that space.
_Q2_PINV = np.linalg.pinv(_Q2.reshape(5, 9).T)  # (5, 9)


def sh_rotation_matrix(R) -> np.ndarray:
    """9x9 matrix ``M`` (or ``(..., 9, 9)`` for ``(..., 3, 3)``) with ``real_sh(R w) = M @ real_sh(w)``.

    Exact for bands 0-2 and any orthogonal ``R``; raises ValueError if ``R`` is not orthogonal.
    """
    R = _f64(R)
    if R.shape[-2:] != (3, 3):
        raise UserError(f"rotation must have shape (..., 3, 3), got {R.shape}")
    eye = np.broadcast_to(np.eye(3), R.shape)
    if not np.allclose(np.swapaxes(R, -1, -2) @ R, eye, atol=1e-6):
        raise UserError("rotation matrix is not orthogonal (R^T R != I)")
    t = np.einsum("...ai,kab,...bj->...kij", R, _Q2, R)  # R^T Q_k R
    m2 = t.reshape(*R.shape[:-2], 5, 9) @ _Q2_PINV.T
    m = np.zeros((*R.shape[:-2], 9, 9))
    m[..., 0, 0] = 1.0
    m[..., 1:4, 1:4] = R  # band 1 in (x, y, z) order transforms like the vector itself
    m[..., 4:, 4:] = m2
    return m


def rotate(light, R):
    """Light after rotating the lighting environment by ``R``: its irradiance at ``R n`` is the old one at ``n``.

    ``light`` (9x3 or Nx9x3) and ``R`` (3x3 or Nx3x3) broadcast; torch ``light`` gives a torch result.
    """
    m = sh_rotation_matrix(R)
    if isinstance(light, torch.Tensor):
        return torch.as_tensor(m, dtype=light.dtype, device=light.device) @ light
    return m @ _f64(light)


def _axis_rotation(deg, axis: int) -> np.ndarray:
    deg = _f64(deg)
    if not np.isfinite(deg).all():  # else a NaN matrix, refused later as "not orthogonal": name the angle here
        raise UserError(f"rotation angle {deg if deg.ndim == 0 else deg[~np.isfinite(deg)][0]} degrees is not "
                        "finite: give a finite number of degrees")
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]  # right-handed: positive angle turns i toward j
    R = np.zeros((*a.shape, 3, 3))
    R[..., axis, axis] = 1.0
    R[..., i, i] = R[..., j, j] = c
    R[..., j, i] = s
    R[..., i, j] = -s
    return R


def rotation_yaw(deg) -> np.ndarray:
    """Rotation about +y (up), counter-clockwise seen from +y (takes +z toward +x); ``(..., 3, 3)``."""
    return _axis_rotation(deg, 1)


def rotation_roll(deg) -> np.ndarray:
    """Rotation about +z (toward the viewer), counter-clockwise seen by the viewer (+x toward +y)."""
    return _axis_rotation(deg, 2)


def rotation_pitch(deg) -> np.ndarray:
    """Rotation about the x axis that takes +z toward +y: a positive pitch raises a frontal light."""
    return _axis_rotation(-_f64(deg), 0)


#: The axes a light rotation video turns about (``rotation_yaw``, ``rotation_roll``).
AXES = ("yaw", "roll")


def rotation_frames(axis: str, frames: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """``(angles in degrees (N,), rotations (N, 3, 3))``: 360 degrees about ``axis`` (:data:`AXES`) in ``frames``
    steps starting at 0: a rotation video's frames (a light's ``rotate``, a sun direction's ``R @ d``)."""
    if axis not in AXES:
        raise UserError(f"rotation axis must be one of {AXES}, got {axis!r}")
    if int(frames) < 1:
        raise UserError(f"frames={frames} must be >= 1")
    angles = np.linspace(0.0, 360.0, int(frames), endpoint=False)
    return angles, (rotation_yaw(angles) if axis == "yaw" else rotation_roll(angles))


def yaw(light, deg):
    """``light`` rotated by ``rotation_yaw(deg)``; a sequence of angles gives ``(N, 9, 3)`` (videos)."""
    return rotate(light, rotation_yaw(deg))


def roll(light, deg):
    """``light`` rotated by ``rotation_roll(deg)``; a sequence of angles gives ``(N, 9, 3)``."""
    return rotate(light, rotation_roll(deg))


def pitch(light, deg):
    """``light`` rotated by ``rotation_pitch(deg)``."""
    return rotate(light, rotation_pitch(deg))


# Rec. 709 luminance would tilt the direction toward green light; the plain RGB mean treats channels alike.
RGB_MEAN = (1 / 3, 1 / 3, 1 / 3)


def dominant_direction(light, channel_weights=RGB_MEAN, eps: float = 1e-12) -> np.ndarray:
    """Unit direction toward the light (``(3,)``, or ``(N, 3)`` for ``(N, 9, 3)``) from band 1.

    Band 1 is the irradiance gradient, (x, y, z) order, combined over RGB with ``channel_weights``
    (default: mean). Where band 1 has norm <= ``eps`` (a uniform light has no direction) this returns
    +z, the frontal light, which casts no visible shadow on a face.
    """
    b1 = _f64(light)[..., 1:4, :] @ _f64(channel_weights)
    norm = np.linalg.norm(b1, axis=-1, keepdims=True)
    frontal = np.broadcast_to(np.array([0.0, 0.0, 1.0]), b1.shape)
    return np.where(norm > eps, b1 / np.maximum(norm, eps), frontal)


def rotation_between(a, b) -> np.ndarray:
    """The 3x3 rotation taking unit vector ``a`` to unit vector ``b`` about their common normal (Rodrigues)."""
    a, b = _f64(a) / np.linalg.norm(a), _f64(b) / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-9:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])  # half turn about any normal
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def light_toward(light, direction) -> np.ndarray:
    """``light`` turned so that its dominant direction is ``direction`` (camera space: x right, y up, z toward the
    viewer): the same ambient, colour and strength, from a new side."""
    d = _f64(direction)
    if d.shape != (3,) or not np.isfinite(d).all() or not np.abs(d).max() > 0:
        raise UserError(f"light direction {np.asarray(direction).tolist()!r} is not a finite non-zero 3-vector")
    d = d / np.abs(d).max()  # the norm of 1e154-sized components overflows to inf (and turned the light a half turn)
    return rotate(light, rotation_between(dominant_direction(light), d))


# ---------------------------------------------------------------------------------------------------------
# Equirectangular env maps (docs/architecture.md): row 0 = +y, theta from +y, phi = 0 at +z, pi/2 at +x.


def envmap_directions(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions ``(H, W, 3)`` of pixel centres and pixel solid angles ``(H, W)`` (sum 4 pi).

    Each solid angle is the exact integral of ``sin theta dtheta dphi`` over the pixel, so band 0 and
    the total are exact for any resolution.
    """
    theta_edges = np.linspace(0.0, math.pi, height + 1)
    theta = 0.5 * (theta_edges[:-1] + theta_edges[1:])
    phi = -math.pi + (np.arange(width) + 0.5) * (2 * math.pi / width)
    st = np.sin(theta)[:, None]
    dirs = np.stack(
        np.broadcast_arrays(st * np.sin(phi)[None], np.cos(theta)[:, None], st * np.cos(phi)[None]), axis=-1
    )
    ring = (np.cos(theta_edges[:-1]) - np.cos(theta_edges[1:])) * (2 * math.pi / width)
    return dirs, np.broadcast_to(ring[:, None], (height, width)).copy()


def project_envmap(env) -> np.ndarray:
    """DECA ``light`` (9x3) of an equirectangular HDR radiance map ``env`` (H, W, 3)."""
    env = _f64(env)
    if env.ndim != 3 or env.shape[-1] != 3:
        raise UserError(f"env map must be (H, W, 3), got {env.shape}")
    dirs, area = envmap_directions(*env.shape[:2])
    coeffs = np.einsum("hwk,hw,hwc->kc", real_sh(dirs), area, env)
    return light_from_radiance(coeffs)


def render_envmap(light, height: int, width: int) -> np.ndarray:
    """Radiance map (H, W, 3) whose projection is ``light``; the raw SH sum, unclipped (it may be < 0)."""
    dirs, _ = envmap_directions(height, width)
    return real_sh(dirs) @ radiance_from_light(light)


# ---------------------------------------------------------------------------------------------------------
def fit(intensity, normals, albedo=1.0, weights=None, ridge: float = 0.0, basis=None) -> np.ndarray:
    """Least-squares ``light`` (9x3) with ``intensity ~ albedo * irradiance(light, normals)``, per channel.

    ``intensity``/``normals`` (N, 3); ``albedo`` scalar, (3,) or (N, 3); ``weights`` (N,) >= 0.
    ``ridge`` adds ``ridge * |l|^2`` to the loss. Without ridge, raises ValueError for N < 9 samples or
    normals whose SH design matrix has rank < 9 (e.g. all equal, or all in one plane). ``basis``: the caller's
    ``sh_basis(normals)`` (N, 9), when it has it already (a robust fit's passes over subsets of one set).
    """
    y = _f64(intensity)
    n = _f64(normals)
    if y.ndim != 2 or y.shape[1] != 3 or n.shape != y.shape:
        raise UserError(f"intensity and normals must both be (N, 3), got {y.shape} and {n.shape}")
    num = y.shape[0]
    alb = np.broadcast_to(_f64(albedo), (num, 3))
    w = np.ones(num) if weights is None else np.broadcast_to(_f64(weights), (num,))
    if np.any(w < 0):
        raise UserError("weights must be non-negative")
    if ridge < 0:
        raise UserError("ridge must be non-negative")
    sw = np.sqrt(w)
    basis = (sh_basis(n) if basis is None else _f64(basis)) * sw[:, None]  # (N, 9)
    if ridge == 0 and np.count_nonzero(sw) < 9:
        raise UserError(
            f"fit needs at least 9 samples with non-zero weight for 9 SH coefficients, got {np.count_nonzero(sw)}"
        )
    out = np.empty((9, 3))
    if ridge > 0 and np.ndim(albedo) <= 1:
        # One albedo per channel: a = albedo_c * basis, so every channel's normal equations share basis' Gram
        # matrix (one (N, 9) product instead of three; equal to the loop below up to rounding).
        gram, rhs = basis.T @ basis, basis.T @ (y * sw[:, None])
        for c in range(3):
            out[:, c] = np.linalg.solve(alb[0, c] ** 2 * gram + ridge * np.eye(9), alb[0, c] * rhs[:, c])
        return out
    for c in range(3):
        a = basis * alb[:, c : c + 1]
        b = y[:, c] * sw
        if ridge > 0:
            # The ridge keeps the 9x9 normal equations well conditioned: solved directly they agree with the
            # augmented least squares to ~1e-12 relative, and skip its SVD rank check (moot here) and its
            # factorisation of the (N + 9, 9) matrix (5x slower for a photo's skin pixels).
            out[:, c] = np.linalg.solve(a.T @ a + ridge * np.eye(9), a.T @ b)
            continue
        s = np.linalg.svd(a, compute_uv=False)
        rank = int(np.sum(s > 1e-9 * s[0])) if s[0] > 0 else 0
        if rank < 9:
            raise UserError(
                f"fit: normals (times albedo of channel {c}) are rank-deficient: the SH design matrix has rank "
                f"{rank} < 9; use normals spread over more directions (not all equal or coplanar) or ridge > 0"
            )
        out[:, c] = np.linalg.lstsq(a, b, rcond=None)[0]
    return out
