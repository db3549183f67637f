"""Target lighting as a user gives it (SPEC 5.2, 5.4, 12): :class:`Targets`, the checked lights, shadow strengths
and key suns a relight decodes under, and where they come from: a 9x3 SH file, another record's light, a
rotation of the input's own light, an equirectangular HDR environment map, and the shadow strength c' a target
gets (:mod:`difareli.data.target_shadow`). The encodings they imply are re-rendered by
:mod:`difareli.render.retarget` (the input's own are used for inversion only).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from difareli.lighting import presets, sh
from difareli.render.retarget import retarget_many
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
        shape, arr = np.shape(arr), np.asarray(arr, dtype=np.float64).reshape(-1)
    except (ValueError, TypeError, EOFError, OSError) as e:
        why = (str(e).splitlines() or [type(e).__name__])[0][:120]
        raise UserError(f"target light file {path} is not 27 numbers ({why}); give a "
                        ".npy 9x3 array or a text file of 27 numbers") from None
    if arr.size == 27 and shape not in ((9, 3), (27,), (1, 27), (27, 1), (1, 9, 3)):
        # a 3x9 (transposed) light read row-major would scramble bands and colours into another light, silently
        fix = "transpose it (light.T)" if shape == (3, 9) else "save it as a 9x3 array"
        raise UserError(f"target light file {path} is a {'x'.join(map(str, shape))} array; a light is 9x3 (9 SH "
                        f"bands of R, G, B: DECA's order) or 27 numbers in that order: {fix}")
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
    env = env[..., :3]
    if (env < 0).any():  # radiance is light arriving: a negative map relit a face with an "anti-light", exit 0
        raise UserError(f"environment map {path}: {int((env < 0).sum())} of {env.size} values are negative (lowest "
                        f"{env.min():.3g}); radiance is >= 0: save the map unshifted (clip it at 0)")
    return env


#: The ways to give a target light: exactly one, or none (the source's own light); an environment map may take a
#: yaw besides (its rotation).
TARGET_KEYS = ("light", "record", "yaw", "roll", "pitch", "envmap", "direction")
#: The keys that turn a light (the source's own, or an environment map's by a yaw).
TURNS = {"yaw": sh.rotation_yaw, "roll": sh.rotation_roll, "pitch": sh.rotation_pitch}


def is_named(value, key: str = "light") -> bool:
    """Whether a ``target.light`` (``key="light"``) or ``target.envmap`` value is a named light, not a file: one of
    :data:`lighting.presets.NAMES`, or for an envmap one of its HDR maps."""
    return isinstance(value, str) and value in (presets.NAMES if key == "light" else presets.ENVMAPS)


def target_lights(source_light: np.ndarray, *, light: str | None = None, other_light: np.ndarray | None = None,
                  yaw: float | None = None, roll: float | None = None, pitch: float | None = None,
                  envmap: str | None = None, direction=None, normals: np.ndarray | None = None) -> np.ndarray:
    """One target as a (9, 3) light: a 9x3 SH file or a named light (``light``: :mod:`difareli.lighting.presets`),
    another record's light, the source's own light turned by a yaw, roll or pitch (degrees) or toward a
    ``direction``, or an environment map (an HDR file, SH-projected, or a named map at the source light's ambient;
    turned by ``yaw`` when given; one way, or an envmap and its yaw: :class:`~difareli.relight.request.Target`);
    nothing given: the source's own light. Its numbers are checked once, where they
    are given (:meth:`~difareli.relight.request.Request.from_config`; a caller that checked nothing hears of a
    non-finite angle from :mod:`difareli.lighting.sh`), and the light's bound once, by :meth:`Targets.of`. A named
    light or a direction is made plausible for the face (``normals``: its normal map; :func:`presets.plausible`)."""
    if other_light is not None:
        return np.asarray(other_light, np.float64)
    if light is not None and not is_named(light):
        return load_sh_file(light)
    if envmap is not None and not is_named(envmap, "envmap"):
        out = sh.project_envmap(load_envmap(envmap))
        return out if yaw is None else sh.yaw(out, yaw)
    src = check_finite(np.asarray(source_light, np.float64), "the source record's light")
    if light is not None or envmap is not None:
        return presets.preset_light(light or envmap, src, normals, yaw=yaw)
    if direction is not None:
        return presets.toward(src, direction, normals)
    turn = next(((TURNS[k], v) for k, v in dict(yaw=yaw, roll=roll, pitch=pitch).items() if v is not None), None)
    return src if turn is None else sh.rotate(src, turn[0](turn[1]))
