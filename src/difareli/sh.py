"""Second-order spherical-harmonics lighting in DECA's convention (SPEC 3).

``E(n) = sum_k l_k c_k H_k(n)`` with the basis ``H = [1, x, y, z, xy, xz, yz, x^2-y^2, 3z^2-1]`` and the
constants ``c_k`` below, which fold the Lambertian convolution into bands 1 and 2 (DECA leaves band 0
without the factor pi: see docs/architecture.md). Functions accept numpy arrays or torch tensors and
return the same kind.
"""

from __future__ import annotations

import math

import numpy as np
import torch

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
