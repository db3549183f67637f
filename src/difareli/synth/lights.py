"""The SynthFaces lighting distribution: an ambient SH environment plus one sun (directional light), and
in SynthFaces v2 (``multi_sun``) up to two more coloured suns: a fill opposite the key and a rim from behind.

A :class:`Light` is rendered exactly (the sun's term ``sun_rgb * visibility * max(0, n.d)`` is ray traced,
so it casts shadows) while its ground-truth ``light`` encoding is the 9x3 SH of the whole thing,
``ambient + sh.directional_light(sun_dir, sun_rgb)`` (SPEC 2/3: the SH a perfect estimator would return).

Intensities are irradiances: an ambient of level ``a`` gives ``E = a`` on every normal (band 0 only),
a sun of intensity ``I`` gives ``E = I`` on a surface facing it. ``sun_dir`` points from the face *toward*
the sun, in camera space (x right, y up, z toward the viewer).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from difareli.errors import UserError
from difareli.lighting import sh
from difareli.lighting.suns import Suns

#: Categories and their sampling weights (see :func:`sample_light`).
CATEGORIES: dict[str, float] = {
    "hard": 0.30,       # strong sun, little ambient: crisp nose/chin/hat cast shadows
    "soft": 0.15,       # overcast: bright sky from above, weak or no sun
    "coloured": 0.15,   # tinted sun and complementary tinted ambient
    "dim": 0.10,        # everything very dark
    "bright": 0.10,     # over-exposed, clips on light skin
    "rim": 0.10,        # sun behind the head, frontal fill
    "grazing": 0.10,    # sun nearly perpendicular to the view: long shadows, half the face dark
}

_C0 = float(sh.SH_CONSTANTS[0])
_C1 = float(sh.SH_CONSTANTS[1])
_C2 = float(sh.SH_CONSTANTS[4])
# Fibonacci sphere used to check that an ambient environment has non-negative irradiance everywhere.
_N_CHECK = 256
_k = np.arange(_N_CHECK) + 0.5
_phi = np.arccos(1 - 2 * _k / _N_CHECK)
_theta = math.pi * (1 + 5**0.5) * _k
_SPHERE = np.stack([np.cos(_theta) * np.sin(_phi), np.sin(_theta) * np.sin(_phi), np.cos(_phi)], axis=-1)


@dataclass(frozen=True)
class Light:
    """One lighting condition: ambient SH (9x3, DECA convention) and a sun (direction, RGB irradiance)."""

    category: str
    ambient: np.ndarray   # (9, 3) float64
    sun_dir: np.ndarray   # (3,) unit vector toward the sun
    sun_rgb: np.ndarray   # (3,) irradiance on a surface facing the sun; all zero = no sun
    #: Extra suns (v2 ``multi_sun``): ``(K, 3)`` unit directions and RGB irradiances, fill and rim lights.
    extra_dirs: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    extra_rgbs: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    extra_names: tuple[str, ...] = ()

    @property
    def has_sun(self) -> bool:
        return bool(np.any(self.sun_rgb > 0))

    def suns(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every sun with light, ``(direction, rgb)``: the key sun first, then the extra ones."""
        out = [(self.sun_dir, self.sun_rgb)] if self.has_sun else []
        return out + [(d, c) for d, c in zip(self.extra_dirs, self.extra_rgbs) if np.any(c > 0)]

    def sh(self) -> np.ndarray:
        """The ground-truth ``light`` encoding (9x3 float32): ambient + SH projection of every sun."""
        full = self.ambient + (sh.directional_light(self.sun_dir, self.sun_rgb) if self.has_sun else 0.0)
        for d, c in zip(self.extra_dirs, self.extra_rgbs):
            full = full + sh.directional_light(d, c)
        return full.astype(np.float32)

    def as_suns(self) -> Suns | None:
        """The same light as :class:`~difareli.lighting.suns.Suns` (every lit sun, the key first, and the ambient),
        or None when no sun has light."""
        lit = self.suns()
        if not lit:
            return None
        return Suns(np.stack([d for d, _ in lit]), np.stack([c for _, c in lit]), self.ambient)

    def meta(self) -> dict:
        out = {"category": self.category, "sun_dir": self.sun_dir.round(6).tolist(),
               "sun_rgb": self.sun_rgb.round(6).tolist()}
        if self.extra_names:
            out["extra_suns"] = [{"name": n, "dir": d.round(6).tolist(), "rgb": c.round(6).tolist()}
                                 for n, d, c in zip(self.extra_names, self.extra_dirs, self.extra_rgbs)]
        return out


def direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector toward a light at ``azimuth`` (0 = from the viewer, +90 = from +x, the image right)
    and ``elevation`` (+90 = from straight above)."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])


def ambient_sh(rng: np.random.Generator, level, *, gradient: float, band2: float) -> np.ndarray:
    """A random low-frequency environment: mean irradiance ``level`` (RGB), a band-1 gradient of relative
    size ``gradient`` biased toward the sky (+y), and band-2 terms of relative size up to ``band2``."""
    level = np.broadcast_to(np.asarray(level, dtype=np.float64), (3,))
    up = np.array([0.0, 1.0, 0.0]) + 0.6 * rng.standard_normal(3)
    up /= np.linalg.norm(up)
    light = np.zeros((9, 3))
    light[0] = level / _C0
    light[1:4] = (gradient / _C1) * up[:, None] * level[None, :]
    light[4:9] = (band2 / _C2) * rng.uniform(-1, 1, size=(5, 1)) / math.sqrt(5) * level[None, :]
    # Keep the environment physical: no normal may receive negative light (shrink the higher bands if so).
    for _ in range(8):
        e = sh.irradiance(light, _SPHERE)
        if e.min() >= 0.1 * level.min():
            break
        light[1:] *= 0.7
    return light


def _tint(rng: np.random.Generator, strength: float) -> np.ndarray:
    # A colour near white, normalised to mean 1 so the tint does not change overall brightness.
    c = np.exp(rng.normal(0.0, strength, 3))
    return c / c.mean()


def _warm_or_cool(rng: np.random.Generator) -> np.ndarray:
    # Sun colour between warm (sunset/tungsten) and cool (shade/LED).
    warm, cool = np.array([1.0, 0.8, 0.55]), np.array([0.75, 0.87, 1.0])
    t = rng.uniform()
    c = warm * (1 - t) + cool * t
    return c / c.mean()


def sample_light(rng: np.random.Generator, category: str | None = None) -> Light:
    """Draw one light; the category is drawn with :data:`CATEGORIES`' weights unless given."""
    if category is None:
        names = list(CATEGORIES)
        p = np.array([CATEGORIES[n] for n in names])
        category = names[rng.choice(len(names), p=p / p.sum())]
    if category not in CATEGORIES:
        raise UserError(f"unknown light category {category!r}; known: {', '.join(CATEGORIES)}")
    white = np.ones(3)
    az, el = rng.uniform(-75, 75), rng.uniform(-15, 60)
    if category == "hard":
        amb, amb_c = rng.uniform(0.15, 0.4), _tint(rng, 0.05)
        sun, sun_c = rng.uniform(0.9, 1.4), _tint(rng, 0.04)
        grad, b2 = rng.uniform(0, 0.4), rng.uniform(0, 0.2)
    elif category == "soft":
        amb, amb_c = rng.uniform(0.7, 1.1), _tint(rng, 0.05)
        sun, sun_c = (0.0 if rng.uniform() < 0.4 else rng.uniform(0.05, 0.3)), white
        grad, b2 = rng.uniform(0.2, 0.6), rng.uniform(0, 0.3)
    elif category == "coloured":
        sun_c = _tint(rng, 0.35) if rng.uniform() < 0.5 else _warm_or_cool(rng)
        amb_c = (1.0 / sun_c) / (1.0 / sun_c).mean() * _tint(rng, 0.1)  # complementary fill
        amb, sun = rng.uniform(0.25, 0.6), rng.uniform(0.6, 1.1)
        grad, b2 = rng.uniform(0, 0.5), rng.uniform(0, 0.3)
    elif category == "dim":
        k = rng.uniform(0.12, 0.35)
        amb, sun = k * rng.uniform(0.3, 0.7), k * rng.uniform(0.3, 1.0)
        amb_c, sun_c = _tint(rng, 0.08), _tint(rng, 0.08)
        grad, b2 = rng.uniform(0, 0.5), rng.uniform(0, 0.2)
    elif category == "bright":
        amb, sun = rng.uniform(0.6, 0.9), rng.uniform(0.9, 1.3)
        amb_c, sun_c = _tint(rng, 0.04), _tint(rng, 0.04)
        grad, b2 = rng.uniform(0, 0.3), rng.uniform(0, 0.2)
    elif category == "rim":
        az = rng.choice([-1, 1]) * rng.uniform(110, 165)
        el = rng.uniform(-10, 50)
        amb, sun = rng.uniform(0.4, 0.7), rng.uniform(0.8, 1.4)
        amb_c, sun_c = _tint(rng, 0.06), _tint(rng, 0.06)
        grad, b2 = rng.uniform(0, 0.4), rng.uniform(0, 0.2)
    else:  # grazing
        az = rng.choice([-1, 1]) * rng.uniform(70, 88)
        el = rng.uniform(-10, 35)
        amb, sun = rng.uniform(0.1, 0.35), rng.uniform(0.9, 1.4)
        amb_c, sun_c = _tint(rng, 0.05), _tint(rng, 0.05)
        grad, b2 = rng.uniform(0, 0.3), rng.uniform(0, 0.2)
    ambient = ambient_sh(rng, amb * amb_c, gradient=grad, band2=b2)
    return Light(category, ambient, direction(az, el), sun * sun_c)


def light_rng(seed: int, group: int, index: int) -> np.random.Generator:
    """The random stream of light ``index`` of light group ``group`` (subjects of one group share lights).

    The trailing ``index + 1`` keeps the key distinct from the subject streams ``[seed, k]``
    (numpy's SeedSequence ignores trailing zeros)."""
    return np.random.default_rng([seed, group, 1, index + 1])


def extra_sun_rng(seed: int, group: int, index: int) -> np.random.Generator:
    """The stream of light ``index``'s extra suns: separate from :func:`light_rng` (key ``2`` instead of
    ``1``), so the ambient and key sun of a light are the same with and without ``multi_sun``."""
    return np.random.default_rng([seed, group, 2, index + 1])


def add_suns(light: Light, rng: np.random.Generator) -> Light:
    """``light`` plus a fill sun (p = 0.7: opposite side of the key, 15-40% of its intensity, tinted) and a
    rim sun (p = 0.5: from behind, 30-80%, tinted), coloured independently of the key (key + fill + rim)."""
    key_az = math.degrees(math.atan2(light.sun_dir[0], light.sun_dir[2]))
    ref = float(light.sun_rgb.mean()) if light.has_sun else float(sh.irradiance(light.ambient, np.eye(3)).mean())
    ref = max(ref, 0.2)
    side = -1.0 if key_az > 0 else 1.0
    names, dirs, rgbs = [], [], []
    if rng.uniform() < 0.7:
        names.append("fill")
        dirs.append(direction(side * rng.uniform(20, 70), rng.uniform(-10, 30)))
        rgbs.append(ref * rng.uniform(0.15, 0.4) * _tint(rng, 0.25))
    if rng.uniform() < 0.5:
        names.append("rim")
        dirs.append(direction(rng.choice([-1, 1]) * rng.uniform(115, 160), rng.uniform(0, 45)))
        rgbs.append(ref * rng.uniform(0.3, 0.8) * _tint(rng, 0.3))
    if not names:
        return light
    return replace(light, extra_dirs=np.array(dirs), extra_rgbs=np.array(rgbs), extra_names=tuple(names))
