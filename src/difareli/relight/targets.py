"""Target lighting as a user gives it, and the target encodings it implies (SPEC 5.2, 5.4, 12).

A target light comes from a 9x3 SH file, another record's light, a yaw/roll rotation of the input's own
light, or an equirectangular HDR environment map. Retargeting re-renders what depends on the light: the
shading reference (from the stored normals), the light itself (for variants that take it as a vector),
DiFaReli's shadow scalar c', and DiFaReli++'s shadow map, ray-marched on the stored depth toward the target's
radiance peak (the input's own map is used for inversion only).
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from difareli.lighting import sh
from difareli.lighting.suns import Suns, sun_direction
from difareli.render.camera import OrthoCamera
from difareli.render.screen_shadow import march_shadows
from difareli.render.visible import MARCH_VISIBLE, visible_march
from difareli.data import encodings
from difareli.data.encodings import normalise_c
from difareli.errors import (TARGET_LIGHT_MAX_ABS, UserError, UserFileNotFoundError, check_finite, check_light,
                             check_number)


@dataclass(frozen=True)
class Targets:
    """N target lights (N, 9, 3) and their shadow logits c' (``None``: the model's own rule), checked once; with
    ``maps`` (N, H, W), the target shadow maps given instead of made (an exact or edited map, an oracle); with
    ``suns``, per target a unit direction (3,) toward its key sun where it is known better than the light's
    radiance peak (``None``: the peak), e.g. found from the cast shadows of the photo whose light it is
    (``render.sun_fit``): the target map is marched toward it."""

    lights: np.ndarray
    shadows: tuple[float | None, ...]
    maps: np.ndarray | None = None
    suns: tuple[np.ndarray | None, ...] | None = None

    @classmethod
    def of(cls, lights, shadows=None, what: str = "target", maps=None, suns=None) -> "Targets":
        """Lights (one 9x3 or a sequence/array of them), optional shadows, target shadow maps and key-sun
        directions, checked finite and in range."""
        arr = np.asarray(lights, dtype=np.float64)
        arr = arr[None] if arr.ndim == 2 else arr
        if arr.ndim != 3 or arr.shape[1:] != (9, 3) or len(arr) == 0:
            raise UserError(f"{what}: expected one or more 9x3 SH lights, got shape {arr.shape}")
        checked = np.stack([check_light(l, f"{what} light {i}", TARGET_LIGHT_MAX_ABS) for i, l in enumerate(arr)])
        cs = [None] * len(checked) if shadows is None else list(shadows)
        if len(cs) != len(checked):
            raise UserError(f"{what}: {len(checked)} target lights but {len(cs)} shadow values")
        cs = [check_number(c, f"{what} shadow strength {i}") for i, c in enumerate(cs)]
        if maps is not None:
            maps = check_finite(np.asarray(maps, dtype=np.float32), f"{what} shadow maps")
            if maps.ndim != 3 or len(maps) != len(checked) or maps.min() < 0 or maps.max() > 1:
                raise UserError(f"{what}: {len(checked)} target lights need {len(checked)} shadow maps (N, H, W) "
                                 f"with values in [0, 1]; got shape {maps.shape}")
        if suns is not None:
            suns = tuple(suns)
            if len(suns) != len(checked):
                raise UserError(f"{what}: {len(checked)} target lights but {len(suns)} sun directions")
            suns = tuple(None if d is None else _unit_direction(d, f"{what} sun direction {i}")
                         for i, d in enumerate(suns))
        return cls(checked, tuple(None if c is None else float(c) for c in cs), maps, suns)

    def __len__(self) -> int:
        return len(self.lights)

    def __getitem__(self, i):
        """``(light, c)`` for an index; a list of them for a slice."""
        if isinstance(i, slice):
            return list(zip(self.lights[i], self.shadows[i]))
        return self.lights[i], self.shadows[i]

    def take(self, start: int, stop: int) -> "Targets":
        """Targets ``start:stop`` (their maps and suns with them)."""
        return Targets(self.lights[start:stop], self.shadows[start:stop],
                       None if self.maps is None else self.maps[start:stop],
                       None if self.suns is None else self.suns[start:stop])

    def retarget(self, arrays: Mapping[str, np.ndarray], names: list[str], start: int = 0, stop: int | None = None
                 ) -> list[dict[str, np.ndarray]]:
        """The encodings ``names`` of ``arrays`` under targets ``start:stop`` (:func:`retarget_many`), the given
        ``maps`` taking the place of the made shadow maps."""
        stop = len(self) if stop is None else min(stop, len(self))
        out = retarget_many(arrays, names, self[start:stop], None if self.suns is None else self.suns[start:stop])
        if self.maps is not None and "shadow_map" in names:  # their size: Relighter.check_inputs
            for k, o in enumerate(out):
                o["shadow_map"] = self.maps[start + k]
        return out


def _unit_direction(d, what: str) -> np.ndarray:
    v = check_finite(np.asarray(d, dtype=np.float64), what)
    norm = float(np.linalg.norm(v)) if v.shape == (3,) else 0.0
    if norm < 1e-6:
        raise UserError(f"{what}: expected a non-zero 3-vector, got {v.tolist()}")
    return v / norm


def load_sh_file(path: str | Path) -> np.ndarray:
    """A 9x3 SH light from ``.npy`` (9x3 or 27) or a text file of 27 numbers (row-major 9x3)."""
    path = Path(path)
    if not path.is_file():
        raise UserFileNotFoundError(f"target light file {path} does not exist")
    try:
        arr = np.load(path, allow_pickle=False) if path.suffix == ".npy" else np.loadtxt(path, dtype=np.float64)
        arr = np.asarray(arr, dtype=np.float64).reshape(-1)
    except (ValueError, TypeError, EOFError, OSError) as e:
        why = (str(e).splitlines() or [type(e).__name__])[0][:120]
        raise UserError(f"target light file {path} is not 27 numbers ({why}); give a "
                        ".npy 9x3 array or a text file of 27 numbers") from None
    if arr.size != 27:
        raise UserError(f"target light file {path} holds {arr.size} numbers; a 9x3 SH light needs 27 "
                        "(row-major, DECA basis order)")
    return check_light(arr.reshape(9, 3), f"target light file {path}", TARGET_LIGHT_MAX_ABS)


def load_envmap(path: str | Path) -> np.ndarray:
    """An equirectangular HDR radiance map HxWx3 (``.npy``, or ``.hdr``/``.exr`` through imageio)."""
    path = Path(path)
    if not path.is_file():
        raise UserFileNotFoundError(f"environment map {path} does not exist")
    if path.suffix == ".npy":
        try:
            env = np.load(path, allow_pickle=False)
        except (ValueError, EOFError, OSError) as e:
            raise UserError(f"environment map {path} is not a readable .npy array ({str(e)[:120]}); save it "
                            "as a float HxWx3 .npy") from None
    else:
        import imageio.v3 as iio

        try:
            env = iio.imread(path)
        except Exception as e:  # imageio raises plugin-specific errors
            raise UserError(f"cannot read environment map {path} ({e}); save it as a float HxWx3 .npy") from e
    if np.asarray(env).dtype.kind not in "biuf":
        raise UserError(f"environment map {path} holds {np.asarray(env).dtype} values, not numbers")
    env = check_finite(np.asarray(env, dtype=np.float64), f"environment map {path}", max_abs=1e30,
                       fix="save finite radiance values")
    if env.ndim != 3 or env.shape[2] < 3 or env.shape[1] != 2 * env.shape[0]:
        raise UserError(f"environment map {path} has shape {env.shape}; expected equirectangular HxWx3 with W = 2H")
    return env[..., :3]


def target_lights(source_light: np.ndarray, *, light: str | None = None, other_light: np.ndarray | None = None,
                  yaw: float | None = None, roll: float | None = None, envmap: str | None = None) -> np.ndarray:
    """Resolve exactly one target specification into a (9, 3) light. Its numbers are checked once, where they are
    given (:meth:`~difareli.relight.request.Request.from_config`; a caller that checked nothing hears of a
    non-finite angle from :mod:`difareli.lighting.sh`), and the light's bound once, by :meth:`Targets.of`."""
    given = {k: v for k, v in dict(light=light, record=other_light, yaw=yaw, roll=roll, envmap=envmap).items()
             if v is not None}
    if len(given) != 1:
        raise UserError(f"give exactly one target (target.light, target.record, target.yaw, target.roll, "
                         f"target.envmap); got {sorted(given) or 'none'}")
    if light is not None:
        return load_sh_file(light)
    if other_light is not None:
        return np.asarray(other_light, np.float64)
    src = check_finite(np.asarray(source_light, np.float64), "the source record's light")
    if yaw is not None:
        return sh.yaw(src, yaw)
    if roll is not None:
        return sh.roll(src, roll)
    return sh.project_envmap(load_envmap(envmap))


def rotation_lights(source_light: np.ndarray, axis: str, frames: int = 60) -> np.ndarray:
    """``frames`` lights rotating the input's own light 360 degrees about ``axis`` (yaw | roll), (N, 9, 3)."""
    return sh.rotate(source_light, sh.rotation_frames(axis, frames)[1])


def rotation_targets(source: Mapping[str, np.ndarray], axis: str, frames: int, *, store=None,
                     given: float | None = None, sun: np.ndarray | None = None) -> tuple[Targets, str]:
    """The targets of a 360-degree rotation video of a source's own light, and a sentence saying where their
    shadow strength c' came from: ``given``; else, for a store record, :func:`video_shadow` (the input's own c
    when shadowed, else the training split's typical shadowed c); else the input's own c (a photo). ``sun``: the
    source light's key sun (``render.sun_fit.key_sun``), turned with the light, toward which each frame's map is
    marched (None: each frame's radiance peak)."""
    own = encodings.shadow_logit(source)
    if store is not None and own is not None:
        c, why = video_shadow(store, own, given)
    else:
        c = given if given is not None else own
        why = f"target c' = {c} ({'given' if given is not None else 'the input own c'})"
    _, rots = sh.rotation_frames(axis, frames)
    lights = sh.rotate(source["light"], rots)
    suns = None if sun is None else list(rots @ np.asarray(sun, np.float64))
    return Targets.of(lights, [c] * len(lights), f"rotation about {axis}", suns=suns), why


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
            out[n] = e.render(arrays, caster if _marched(n) else light, shadow)
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


# ------------------------------------------------------------------------------------------ target c policy
#: A record counts as shadowed when its cast shadows remove at least this share of the light (c >= logit of it).
SHADOWED_SHARE = 0.01
_TYPICAL_C: dict[tuple[str, str], float | None] = {}


def is_shadowed(c: float) -> bool:
    """Whether a shadow logit ``c`` means a visible cast shadow (share >= ``SHADOWED_SHARE``)."""
    return c >= math.log(SHADOWED_SHARE / (1 - SHADOWED_SHARE))


def typical_shadowed_c(shadows) -> float | None:
    """The median c of the records whose cast shadows remove at least ``SHADOWED_SHARE`` of the light."""
    c = np.asarray(shadows, dtype=np.float64).reshape(-1)
    shadowed = c[np.isfinite(c) & (c >= math.log(SHADOWED_SHARE / (1 - SHADOWED_SHARE)))]
    return float(np.median(shadowed)) if shadowed.size else None


def split_typical_c(store, split: str = "train") -> float | None:
    """:func:`typical_shadowed_c` of the stored ``shadow`` of ``split``'s records (cached per store)."""
    key = (str(store.root), split)
    if key not in _TYPICAL_C:
        ids = store.ids(split=split) if store.available("shadow") else []
        _TYPICAL_C[key] = typical_shadowed_c([store.read(r, ["shadow"])["shadow"][0] for r in ids]) if ids else None
    return _TYPICAL_C[key]


def stored_shadow_is_estimate(store) -> bool:
    """Whether a store's ``shadow`` is what a user has (an estimator's c): photo stores and SynthFaces
    ``inputs=estimated`` (v3) or ``estimated_light`` (v2); a SynthFaces ``inputs=exact`` store holds the exact c
    there (an oracle)."""
    meta = store.store_meta
    return meta.get("generator") != "synthfaces" or meta.get("inputs") in ("estimated", "estimated_light")


def target_shadow_of(store, record_id: str, *, oracle: bool = False, split: str = "train") -> tuple[float | None, str]:
    """``(c', how)``: the shadow strength a user has for a target given by ``record_id``'s image.

    ``oracle``: the exact c (``shadow_gt``, else ``shadow``). Otherwise the stored ``shadow`` when it is an
    estimate (:func:`stored_shadow_is_estimate`), else the stated policy: ``split``'s median shadowed c."""
    if not store.available("shadow"):
        return None, "no target c (the store has no 'shadow' encoding)"
    if oracle:
        name = "shadow_gt" if store.available("shadow_gt") else "shadow"
        return encodings.shadow_logit(store.read(record_id, [name]), name), "exact c (oracle)"
    if stored_shadow_is_estimate(store):
        return (encodings.shadow_logit(store.read(record_id, ["shadow"])),
                "c estimated from the target image (stored 'shadow': the shadow classifier)")
    c = split_typical_c(store, split)
    if c is None:
        raise UserError(f"store {store.root} holds only exact shadow c and its {split} split has no shadowed record to "
                        "take a typical c from; use an inputs=estimated store or set oracle_shadow=true")
    return c, f"c = {c:.3f}, the {split} split's median shadowed c (the store holds only exact c)"


def video_shadow(store, record_c: float | None, given: float | None, split: str = "train") -> tuple[float, str]:
    """The shadow strength c' for every frame of a video and a sentence saying where it came from: ``given``;
    else the input's own c when it is shadowed; else the median shadowed c of ``split`` (the training split)."""
    if given is not None:
        return float(given), f"target c' = {float(given):.3f} (given: target.shadow)"
    if record_c is not None and is_shadowed(record_c):
        return record_c, f"target c' = {record_c:.3f} (the input's own c: it has a cast shadow)"
    c = split_typical_c(store, split)
    own = "no 'shadow' encoding" if record_c is None else f"c = {record_c:.2f}"
    if c is None:
        raise UserError(f"the input has no cast shadow ({own}) and the {split} split of {store.root} has no shadowed "
                        "record to take a typical c from; give target.shadow=<logit c'>")
    return c, (f"target c' = {c:.3f} (the input has no cast shadow, {own}: median c of the {split} split's "
               f"shadowed records, share >= {SHADOWED_SHARE})")
