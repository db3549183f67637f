"""The encodings that depend on the light, re-rendered under a target light (SPEC 5.2, 5.4, 12).

Retargeting re-renders what depends on the light from a record's stored geometry: the shading reference (from the
stored normals), the light itself (for variants that take it as a vector), DiFaReli's shadow scalar c', and
DiFaReli++'s shadow map, ray-marched on the stored depth toward the target's radiance peak or its key sun. The
encoding registry (:mod:`difareli.data.encodings`) says which encodings depend on the light and which of
:data:`RENDERERS` re-renders each; the one shadow-map maker is described by :func:`shadow_maker`.
"""

from __future__ import annotations

import inspect
from typing import Mapping

import numpy as np

from difareli.data import encodings
from difareli.data.encodings import normalise_c
from difareli.errors import UserError
from difareli.lighting import sh
from difareli.lighting.suns import Suns, sun_direction
from difareli.render.camera import OrthoCamera
from difareli.render.screen_shadow import march_shadows
from difareli.render.visible import MARCH_VISIBLE, visible_march


#: Where :func:`retarget_many` puts the cast shadows it ray-marched for all its targets at once (keyed by the
#: light direction's bytes), so each target's ``shadow_map`` re-render reads its map instead of marching again.
CASTS_KEY = "_cast_shadows"


def shadow_maker() -> dict:
    """The one shadow-map maker, described: what made a relight's target maps (and the training maps of
    ``difareli-shadow-maps maker=march``): the depth-map march toward the light's suns (an SH light: its radiance
    peak), with the march's settings (its defaults, read from its signature, so a change of them is a change of
    maker). A store records it beside maps it made, a checkpoint the maker of the maps it trained on; a relight
    warns when the two differ (:func:`check_maker`)."""
    params = inspect.signature(march_shadows).parameters
    settings = {k: v.default for k, v in params.items() if v.default is not inspect.Parameter.empty and k != "normal"}
    return {"name": "march", "toward": "every sun of the light (an SH light: one toward its radiance peak)",
            "attached": "n.d <= 0 is not cast (stored normals where known, else from the depth)",
            "visible": MARCH_VISIBLE, **settings}


#: Training maps that are the renderer's exact shadows (``difareli-shadow-maps maker=visible``), not another maker:
#: what every maker approximates. A model trained on them follows the march's maps (0.86-0.94 and 0.67-0.76 of a
#: real cast shadow's darkening with the march toward the exact suns and toward a fitted light, after 604 and 2,170
#: steps: docs/shadow_maps.md, section 4), so :func:`check_maker` does not warn about them.
EXACT_MAPS = ("visible",)


def check_maker(trained_on: Mapping | None, what: str = "this model") -> str | None:
    """A warning (one sentence naming both) when ``trained_on`` (the maker of a model's training maps, as a
    checkpoint records it) differs from the maker of a relight's target maps; None when they agree, when it
    trained on the exact shadows (:data:`EXACT_MAPS`) or the checkpoint does not say (older checkpoints)."""
    if not trained_on or trained_on.get("name") in EXACT_MAPS:
        return None
    now = shadow_maker()
    if dict(trained_on) == now:
        return None
    differs = sorted(k for k in set(now) | set(trained_on) if now.get(k) != trained_on.get(k))
    how = "" if trained_on.get("name") != now["name"] else f" (they differ in {', '.join(differs)})"
    return (f"{what} trained on shadow maps made by {_describe(trained_on)}, but this relight's target maps are made "
            f"by {_describe(now)}{how}: it may not follow them; retrain on `difareli-shadow-maps maker=march` maps")


def _describe(maker: Mapping) -> str:
    rest = ", ".join(f"{k}={v}" for k, v in maker.items() if k not in ("name", "toward", "attached"))
    return f"{maker.get('name', '?')}" + (f" ({rest})" if rest else "")


def map_direction(light: "np.ndarray | Suns") -> np.ndarray:
    """Where a target map is marched: an SH light's radiance peak (``lighting.suns.sun_direction``), a single
    sun's direction."""
    return light.dirs[0] if isinstance(light, Suns) else sun_direction(light)


def cast_shadows(arrays: Mapping[str, np.ndarray], lights) -> np.ndarray:
    """Binary cast-shadow maps (N, H, W) toward each light's :func:`map_direction` (SH lights or single
    ``Suns``), ray-marched on the stored depth in one batched march; a point turned away from the light (known
    normal, n.d <= 0) is in attached, not cast, shadow."""
    depth = np.asarray(arrays["depth"], dtype=np.float64)
    normal = np.asarray(arrays["normal"], dtype=np.float64)
    cam = OrthoCamera(*np.asarray(arrays["cam"], dtype=np.float64).tolist())
    dirs = np.stack([map_direction(light) for light in lights])
    # The stored normals decide which points face the light where they are known (the march estimates them from
    # the depth elsewhere): on v3's test split 0.463 -> 0.484 IoU toward the key sun, against filtering afterwards.
    return march_shadows(depth, depth != 0, cam, dirs, normal=normal)


def target_shadow_map(arrays: Mapping[str, np.ndarray], light: "np.ndarray | Suns", c: float,
                      c_range=None) -> np.ndarray:
    """Binary cast-shadow map ray-marched on the stored depth, times the normalised shadow strength ``c`` (the
    ``shadow_map`` encoding's definition). ``light``: an SH light (the map toward its radiance peak) or its
    suns (``lighting.suns.Suns``: one sun, the map toward it; several, e.g. a SynthFaces header's: the visibly
    shadowed pixels under them, ``render.visible.visible_march``). ``c_range``: the store's c range
    (``encodings.store_c_range``), else the one the arrays carry under ``encodings.C_RANGE_KEY`` (SynthFaces v3
    readers put it there), else the fixed range."""
    if isinstance(light, Suns) and len(light.dirs) > 1:
        cam = OrthoCamera(*np.asarray(arrays["cam"], dtype=np.float64).tolist())
        cast = visible_march(arrays["depth"], np.asarray(arrays["normal"], np.float64), cam, light)
    else:  # one sun: visibly shadowed is cast (render.visible), so the plain march, batched by retarget_many
        marched = arrays.get(CASTS_KEY, {}).get(map_direction(light).tobytes())
        cast = marched if marched is not None else cast_shadows(arrays, [light])[0]
    c_range = c_range if c_range is not None else encodings.store_c_range(arrays)
    return (cast * normalise_c(c, c_range)).astype(np.float32)


def render_shading(arrays: Mapping[str, np.ndarray], light: np.ndarray, shadow: float | None = None) -> np.ndarray:
    """The shading reference under ``light`` from the stored normals (the ``shading`` encoding's re-render)."""
    normal = np.asarray(arrays["normal"], dtype=np.float64)
    mask = encodings.known_normals(normal)
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
        raise UserError("a target shadow map needs a shadow strength: give target.shadow or a 'shadow' encoding")
    return target_shadow_map(arrays, light, shadow)


#: The re-render of each kind the encoding registry names (``Encoding.rerender``): ``f(arrays, light, shadow)``.
RENDERERS = {"light": render_light, "shadow": render_shadow, "shadow_map": render_shadow_map,
             "shading": render_shading}


def retarget(arrays: Mapping[str, np.ndarray], names: list[str], light: np.ndarray,
             shadow: float | None = None, sun: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The encodings ``names`` under a target ``light`` (and shadow strength ``shadow``, a logit c'),
    re-rendering only those the encoding registry marks light-dependent; the rest are the input's own.
    Without ``shadow`` the input's own c (its ``shadow`` encoding, when stored) is kept. ``sun``: the direction
    the cast-shadow maps are marched toward (default: the light's radiance peak)."""
    if shadow is None and "shadow" in arrays:
        shadow = encodings.shadow_logit(arrays)
    caster = light if sun is None else Suns.of_sh(light, sun)
    out = {}
    for n in names:
        e = encodings.get(n)
        if e.light_dependent:
            out[n] = RENDERERS[e.rerender](arrays, caster if _marched(n) else light, shadow)
        else:
            out[n] = arrays[n]
    return out


def _marched(name: str) -> bool:
    """Whether an encoding is a cast-shadow map marched on the depth (it takes the light's sun)."""
    e = encodings.get(name)
    return e.light_dependent and "depth" in e.needs


def retarget_many(arrays: Mapping[str, np.ndarray], names: list[str], pairs,
                  suns=None) -> list[dict[str, np.ndarray]]:
    """:func:`retarget` for each ``(light, shadow)`` of ``pairs`` (and its ``suns`` direction, None: the
    light's radiance peak); the cast shadows of all their lights are ray-marched first in one batched march (a
    video's 60 frames: one march, not 60)."""
    pairs = list(pairs)
    suns = [None] * len(pairs) if suns is None else list(suns)
    casters = [light if d is None else Suns.of_sh(light, d) for (light, _), d in zip(pairs, suns)]
    if any(_marched(n) for n in names) and len(pairs) > 1 and "depth" in arrays:
        keys = [map_direction(c).tobytes() for c in casters]
        arrays = {**arrays, CASTS_KEY: dict(zip(keys, cast_shadows(arrays, casters)))}
    return [retarget(arrays, names, light, shadow, d) for (light, shadow), d in zip(pairs, suns)]
