"""Named target lights, defined once: the app's preset buttons and ``difareli-relight target.light=<name>`` /
``target.envmap=<name>`` both light a face with them.

:data:`DIRECTIONS`: five key-light directions (camera space, ``docs/architecture.md``: x to the image's right, y up,
z toward the viewer); the source's own light is turned toward one (``sh.light_toward``: its ambient, colour and
strength kept). :data:`ENVMAPS`: small procedural HDR environment maps (equirectangular, the same doc's
convention), so that "pick an HDR map" works offline without shipping image files; each is projected to SH
(``sh.project_envmap``) and scaled so that its ambient (band 0, mean over RGB) equals the source light's: the model
sees light of the strength it was trained on, from the map's directions and colours.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from difareli.lighting import sh

H, W = 32, 64

#: name -> (direction [x, y, z], what it is). "left" is the image's left (the viewer's).
DIRECTIONS: dict[str, tuple[tuple[float, float, float], str]] = {
    "left": ((-1.0, 0.15, 0.45), "a key light from the image's left"),
    "right": ((1.0, 0.15, 0.45), "a key light from the image's right"),
    "top": ((0.0, 1.0, 0.35), "a light from above"),
    "rim": ((0.0, 0.35, -1.0), "a back light behind the head (rim light): the face darkens"),
    "front": ((0.0, 0.0, 1.0), "a light from the camera: flat"),
}


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


#: Every named light: the directions, then the HDR maps.
NAMES = (*DIRECTIONS, *ENVMAPS)


def preset_light(name: str, like: np.ndarray) -> np.ndarray:
    """The named light (:data:`NAMES`) for a face whose own light is ``like`` (9, 3): ``like`` turned toward a
    direction, or an HDR map's light at its ambient."""
    if name in DIRECTIONS:
        return sh.light_toward(np.asarray(like, np.float64), DIRECTIONS[name][0])
    return envmap_light(name, like)
