"""Small procedural HDR environment maps for the app (equirectangular, ``docs/architecture.md``'s convention), so
that "pick an HDR map and a rotation" works offline without shipping image files.

Each map is projected to SH (``sh.project_envmap``) and scaled so that its ambient (band 0, mean over RGB) equals
the source light's: the model sees light of the strength it was trained on, from the map's directions and
colours. A rotation is a yaw of the projected light.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from difareli.lighting import sh

H, W = 32, 64


def _lobe(dirs: np.ndarray, towards, sharpness: float) -> np.ndarray:
    d = np.asarray(towards, np.float64)
    return np.exp(sharpness * (dirs @ (d / np.linalg.norm(d)) - 1.0))


def _sunset(dirs: np.ndarray) -> np.ndarray:
    up = np.clip(dirs[..., 1], 0, 1)[..., None]
    sky = up * np.array([0.25, 0.35, 0.6]) + 0.05
    return sky + 6.0 * _lobe(dirs, [0.8, 0.15, 0.55], 60.0)[..., None] * np.array([1.0, 0.6, 0.3])


def _studio(dirs: np.ndarray) -> np.ndarray:
    key = 5.0 * _lobe(dirs, [-0.7, 0.4, 0.6], 12.0)
    fill = 1.5 * _lobe(dirs, [0.8, 0.1, 0.6], 8.0)
    return (key + fill + 0.05)[..., None] * np.ones(3)


def _overcast(dirs: np.ndarray) -> np.ndarray:
    return (0.2 + 0.8 * np.clip(dirs[..., 1], 0, 1))[..., None] * np.array([0.9, 0.95, 1.0])


def _window(dirs: np.ndarray) -> np.ndarray:
    side = 4.0 * (np.abs(dirs[..., 1]) < 0.4) * (dirs[..., 0] > 0.75)
    return (side + 0.08)[..., None] * np.array([0.95, 1.0, 1.05])


ENVMAPS = {"sunset": _sunset, "studio": _studio, "overcast": _overcast, "window": _window}


@cache
def envmap(name: str) -> np.ndarray:
    """The radiance map (H, W, 3) called ``name``."""
    dirs, _ = sh.envmap_directions(H, W)
    return ENVMAPS[name](dirs)


def envmap_light(name: str, like: np.ndarray) -> np.ndarray:
    """The map's SH light (9, 3), scaled to the ambient of the light ``like``."""
    light = sh.project_envmap(envmap(name))
    scale = float(np.mean(np.asarray(like, np.float64)[0])) / float(np.mean(light[0]))
    return light * max(scale, 1e-3)
