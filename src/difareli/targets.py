"""Target lighting as a user gives it, and the target encodings it implies (SPEC 5.2, 5.4, 12).

A target light comes from a 9x3 SH file, another record's light, a yaw/roll rotation of the input's own
light, or an equirectangular HDR environment map. Retargeting re-renders what depends on the light: the
shading reference (from the stored normals), the light itself (for variants that take it as a vector),
DiFaReli's shadow scalar c', and DiFaReli++'s shadow map, ray-marched on the stored depth toward the target's
dominant direction (the input's own map is used for inversion only).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from difareli import sh
from difareli.render.camera import OrthoCamera
from difareli.render.screen_shadow import march_shadow
from difareli import encodings
from difareli.encodings import normalise_c


def load_sh_file(path: str | Path) -> np.ndarray:
    """A 9x3 SH light from ``.npy`` (9x3 or 27) or a text file of 27 numbers (row-major 9x3)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"target light file {path} does not exist")
    arr = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, dtype=np.float64).reshape(-1)
    arr = np.asarray(arr, dtype=np.float64)
    if arr.size != 27:
        raise ValueError(f"target light file {path} holds {arr.size} numbers; a 9x3 SH light needs 27 "
                         "(row-major, DECA basis order)")
    return arr.reshape(9, 3)


def load_envmap(path: str | Path) -> np.ndarray:
    """An equirectangular HDR radiance map HxWx3 (``.npy``, or ``.hdr``/``.exr`` through imageio)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"environment map {path} does not exist")
    if path.suffix == ".npy":
        env = np.load(path)
    else:
        import imageio.v3 as iio

        try:
            env = iio.imread(path)
        except Exception as e:  # imageio raises plugin-specific errors
            raise ValueError(f"cannot read environment map {path} ({e}); save it as a float HxWx3 .npy") from e
    env = np.asarray(env, dtype=np.float64)
    if env.ndim != 3 or env.shape[2] < 3 or env.shape[1] != 2 * env.shape[0]:
        raise ValueError(f"environment map {path} has shape {env.shape}; expected equirectangular HxWx3 with W = 2H")
    return env[..., :3]


def target_lights(source_light: np.ndarray, *, light: str | None = None, other_light: np.ndarray | None = None,
                  yaw: float | None = None, roll: float | None = None, envmap: str | None = None) -> np.ndarray:
    """Resolve exactly one target specification into a (9, 3) light."""
    given = {k: v for k, v in dict(light=light, record=other_light, yaw=yaw, roll=roll, envmap=envmap).items()
             if v is not None}
    if len(given) != 1:
        raise ValueError(f"give exactly one target (target.light, target.record, target.yaw, target.roll, "
                         f"target.envmap); got {sorted(given) or 'none'}")
    if light is not None:
        return load_sh_file(light)
    if other_light is not None:
        return np.asarray(other_light, dtype=np.float64)
    if yaw is not None:
        return sh.yaw(source_light, float(yaw))
    if roll is not None:
        return sh.roll(source_light, float(roll))
    return sh.project_envmap(load_envmap(envmap))


def rotation_lights(source_light: np.ndarray, axis: str, frames: int = 60) -> np.ndarray:
    """``frames`` lights rotating the input's own light 360 degrees about ``axis`` (yaw | roll), (N, 9, 3)."""
    angles = np.linspace(0.0, 360.0, frames, endpoint=False)
    if axis == "yaw":
        return sh.yaw(source_light, angles)
    if axis == "roll":
        return sh.roll(source_light, angles)
    raise ValueError(f"rotation axis must be 'yaw' or 'roll', got {axis!r}")


def target_shadow_map(arrays: Mapping[str, np.ndarray], light: np.ndarray, c: float) -> np.ndarray:
    """Binary cast-shadow map toward ``light``'s dominant direction, ray-marched on the stored depth, times
    the normalised shadow strength ``c`` (the ``shadow_map`` encoding's definition)."""
    depth = np.asarray(arrays["depth"], dtype=np.float64)
    normal = np.asarray(arrays["normal"], dtype=np.float64)
    cam = OrthoCamera(*np.asarray(arrays["cam"], dtype=np.float64).tolist())
    hit = depth != 0
    d = sh.dominant_direction(light)
    cast = march_shadow(depth, hit, cam, d)
    # Where the face normal is known, a point turned away from the light is in attached, not cast, shadow.
    known = np.linalg.norm(normal, axis=-1) > 0.5
    cast &= ~(known & (normal @ d <= 0))
    return (cast * normalise_c(c)).astype(np.float32)


def render_shading(arrays: Mapping[str, np.ndarray], light: np.ndarray, shadow: float | None = None) -> np.ndarray:
    """The shading reference under ``light`` from the stored normals (the ``shading`` encoding's re-render)."""
    normal = np.asarray(arrays["normal"], dtype=np.float64)
    mask = np.linalg.norm(normal, axis=-1) > 0.5
    return sh.shading_reference(light, normal, mask=mask).astype(np.float32)


def render_light(arrays: Mapping[str, np.ndarray], light: np.ndarray, shadow: float | None = None) -> np.ndarray:
    """The target light itself (variants that take the light as a vector)."""
    return np.asarray(light, dtype=np.float32)


def render_shadow(arrays: Mapping[str, np.ndarray], light: np.ndarray, shadow: float | None = None) -> np.ndarray:
    """DiFaReli's shadow scalar c': the target's when given, else the input's own."""
    if shadow is None:
        return np.asarray(arrays["shadow"], dtype=np.float32)
    return np.array([shadow], dtype=np.float32)


def render_shadow_map(arrays: Mapping[str, np.ndarray], light: np.ndarray, shadow: float | None = None) -> np.ndarray:
    """DiFaReli++'s shadow map toward ``light`` with strength ``shadow`` (a logit c')."""
    if shadow is None:
        raise ValueError("a target shadow map needs a shadow strength: give target.shadow or a 'shadow' encoding")
    return target_shadow_map(arrays, light, shadow)


def retarget(arrays: Mapping[str, np.ndarray], names: list[str], light: np.ndarray,
             shadow: float | None = None) -> dict[str, np.ndarray]:
    """The encodings ``names`` under a target ``light`` (and shadow strength ``shadow``, a logit c'),
    re-rendering only those the encoding registry marks light-dependent; the rest are the input's own.
    Without ``shadow`` the input's own c (its ``shadow`` encoding, when stored) is kept."""
    if shadow is None and "shadow" in arrays:
        shadow = float(np.asarray(arrays["shadow"]).reshape(-1)[0])
    out = {}
    for n in names:
        e = encodings.get(n)
        out[n] = e.render(arrays, light, shadow) if e.light_dependent else arrays[n]
    return out
