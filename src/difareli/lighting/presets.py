"""Named target lights, defined once: the app's preset buttons and ``difareli-relight target.light=<name>`` /
``target.envmap=<name>`` both light a face with them.

:data:`DIRECTIONS`: five key-light directions (camera space, ``docs/architecture.md``: x to the image's right, y up,
z toward the viewer); the source's own light is turned toward one (``sh.light_toward``: its ambient, colour and
strength kept). :data:`ENVMAPS`: small procedural HDR environment maps (equirectangular, the same doc's
convention), so that "pick an HDR map" works offline without shipping image files; each is projected to SH
(``sh.project_envmap``).

Every named light, and every direction the app turns a light toward, is made physically plausible for the face it
lights (:func:`plausible`): its key (SH bands 1-2) weakened where it lies behind the face (:func:`behind`), ambient
added until its darkest face normal gets at least :data:`FILL` of the face's
mean irradiance (so never negative), then scaled so that its mean irradiance on the face equals the source light's
(the source's energy kept, the target's colour and direction unchanged). Without this, a source light turned to
``top`` or ``rim``, or a map at the source's ambient, gave negative irradiance on much of a frontal face and took a
third to a half of its luminance (docs/photo_quality.md).
"""

from __future__ import annotations

from functools import cache

import numpy as np

from difareli.data.encodings import known_normals
from difareli.lighting import sh
from difareli.lighting.suns import fibonacci_sphere

H, W = 32, 64

#: The darkest face normal's irradiance under a named light, as a share of the face's mean: the 25th percentile of
#: that share over 300 training lights of data/sf_est_64 (median 0.46, 5th percentile -0.08), so three in four
#: training lights fill the face more than a named light does.
FILL = 0.3
#: The normals a face can show the camera (a sphere's visible half, z >= 0): a named light is non-negative on all of
#: them, whatever face it lights.
VISIBLE = (lambda d: d[d[:, 2] >= 0])(fibonacci_sphere(2048))

#: name -> (direction [x, y, z], what it is). "left" is the image's left (the viewer's).
DIRECTIONS: dict[str, tuple[tuple[float, float, float], str]] = {
    "left": ((-1.0, 0.15, 0.45), "a key light from the image's left"),
    "right": ((1.0, 0.15, 0.45), "a key light from the image's right"),
    "top": ((0.0, 1.0, 0.35), "a light from above"),
    "rim": ((0.0, 0.35, -1.0), "a back light behind the head (rim light): bright edges, a dimmer face"),
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


def envmap_light(name: str) -> np.ndarray:
    """The map's SH light (9, 3), as projected (:func:`plausible` scales it to a face)."""
    return sh.project_envmap(envmap(name))


#: Every named light: the directions, then the HDR maps.
NAMES = (*DIRECTIONS, *ENVMAPS)


def face_normals(normals: np.ndarray | None) -> np.ndarray:
    """The unit normals of a face (``normals``: a stored normal map, 0 off the mesh, or (M, 3)); :data:`VISIBLE`
    without any."""
    if normals is None:
        return VISIBLE
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    n = n[known_normals(n)]
    return n / np.linalg.norm(n, axis=-1, keepdims=True) if len(n) else VISIBLE


def plausible(light: np.ndarray, like: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
    """``light`` (9, 3) made plausible for a face whose own light is ``like`` and whose normals are ``normals``
    (:func:`face_normals`): its key weakened where it lies behind them (:func:`behind`), then per channel, the
    ambient (band 0) raised until the darkest of the face's and
    :data:`VISIBLE`'s normals gets at least :data:`FILL` of the face's mean irradiance, then one factor for all
    channels that makes the face's mean irradiance (mean over RGB) equal ``like``'s."""
    light = np.array(light, np.float64)
    n = face_normals(normals)
    light[1:] *= behind(light, n)
    e = sh.irradiance(light, n)  # (M, 3)
    darkest = np.minimum(e.min(0), sh.irradiance(light, VISIBLE).min(0))
    # min + a >= FILL (mean + a): the ambient a each channel needs (0 when it already has it).
    add = np.maximum(FILL * e.mean(0) - darkest, 0.0) / (1.0 - FILL)
    light[0] += add / sh.SH_CONSTANTS[0]
    own = float(sh.irradiance(np.asarray(like, np.float64), n).mean())
    now = float(e.mean() + add.mean())  # > 0: the darkest normal gets FILL of it, or more
    # A source light with no energy on its face (a black photo) leaves nothing to keep: the light stays as filled.
    return light * (own / now) if own > 0 and now > 0 else light


def behind(light: np.ndarray, n: np.ndarray) -> float:
    """The factor on ``light``'s key (SH bands 1-2) that lets it vary over the normals ``n`` no more than a real key
    light from its dominant direction d can: ``max(0, n.d)`` spans ``max(0, c_max) - max(0, c_min)`` over them, the
    SH key's linear term ``(c_max - c_min) / 2`` (``1/4 + c/2 + ...``, the clamped cosine's projection). 1 where some
    normal faces the light (``left``, ``top``, ``front``); 0 where all face away: a light wholly behind the face
    lights it by the fill alone. Without it the linear term, turned behind the head, lit the normals that face away
    least (forehead, nose bridge) up to 8 times more than the rest (issue 61's bright patch; docs/photo_quality.md)."""
    c = n @ sh.dominant_direction(light)
    span = float(c.max() - c.min())
    # A trace of the key (1e-6) stays where all face away: its direction still says where the light is (its
    # description, the cast-shadow march) at no visible cost.
    return 1.0 if span <= 0 else min(1.0, max(2.0 * (max(c.max(), 0.0) - max(c.min(), 0.0)) / span, 1e-6))


def preset_light(name: str, like: np.ndarray, normals: np.ndarray | None = None, yaw: float | None = None
                 ) -> np.ndarray:
    """The named light (:data:`NAMES`) for a face whose own light is ``like`` (9, 3) and normals ``normals``:
    ``like`` turned toward a direction, or an HDR map's light turned by ``yaw`` degrees, made :func:`plausible`."""
    if name in DIRECTIONS:
        return toward(like, DIRECTIONS[name][0], normals)
    light = envmap_light(name)
    return plausible(light if yaw is None else sh.yaw(light, yaw), like, normals)


def toward(like: np.ndarray, direction, normals: np.ndarray | None = None) -> np.ndarray:
    """``like`` turned toward ``direction`` (``sh.light_toward``) and made :func:`plausible` for the face."""
    return plausible(sh.light_toward(np.asarray(like, np.float64), direction), like, normals)
