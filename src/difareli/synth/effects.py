"""SynthFaces v2 appearance effects: which are on (``Effects``, the ``realism`` presets) and their models.

Image formation with every effect on (linear, no gamma; ``docs/synthfaces_v2.md``)::

    E(p)     = AO(p) E_amb(n) + sum_i sun_i V_i(p) wrap_w(n . d_i)            (w per RGB channel on skin)
    S(p)     = k_s(part) sum_i sun_i V_i(p) (s + 8) / 8 (n . h_i)^s max(0, n . d_i)   (Blinn-Phong, white)
    image(p) = clip(albedo(p) E(p) + S(p), 0, 1)

- ``specular``: Blinn-Phong lobe per sun, half vector ``h_i = unit(d_i + v)`` with the orthographic view
  ``v = +z``; per-part strength ``k_s`` and exponent ``s`` (:data:`SPECULAR_PARTS`), the forehead (skin above
  the brows) oily (``FOREHEAD_GAIN``); the ``(s + 8) / 8`` factor keeps the lobe's energy roughly constant
  over exponents. Suns only: the ambient environment adds no specular term.
- ``subsurface``: per-channel wrap lighting ``wrap_w(x) = max(0, (x + w) / (1 + w))`` of every sun on the skin
  parts (:data:`SSS_PARTS`), with ``w`` larger for red (:data:`WRAP_RGB`): light reaches past the terminator,
  redder the farther. ``w = 0`` is Lambert. The ambient term is already a smooth cosine convolution.
- ``ambient_occlusion``: the ambient term times ray-traced AO (``render.ao``), once per subject.
- ``multi_sun``: key + fill + rim coloured suns (``lights.add_suns``); each sun casts its own shadow.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Mapping

import numpy as np

from difareli.data.encodings import PART_INDEX
from difareli.errors import UserError

#: The realism presets: ``lambertian`` is SynthFaces v1 (bit-identical images for the same seed).
REALISM_PRESETS: dict[str, dict[str, bool]] = {
    "lambertian": {"specular": False, "subsurface": False, "ambient_occlusion": False, "multi_sun": False},
    "full": {"specular": True, "subsurface": True, "ambient_occlusion": True, "multi_sun": True},
}
#: Part -> (specular strength k_s, Blinn-Phong exponent s): dry cheeks, oily nose, wet lips and eyes, glossy hair.
SPECULAR_PARTS: dict[str, tuple[float, float]] = {
    "skin": (0.035, 12.0), "nose": (0.10, 40.0), "neck": (0.02, 10.0),
    "u_lip": (0.12, 60.0), "l_lip": (0.14, 60.0), "mouth": (0.05, 30.0),
    "l_eye": (0.30, 250.0), "r_eye": (0.30, 250.0), "hair": (0.07, 25.0),
    "l_brow": (0.02, 10.0), "r_brow": (0.02, 10.0), "hat": (0.04, 20.0), "clothes": (0.02, 8.0),
}
#: Oily forehead: skin pixels above the brows get this times the skin strength, and the nose's exponent.
FOREHEAD_GAIN = 2.5
#: Wrap widths (R, G, B) of the subsurface approximation: red scatters farthest in skin.
WRAP_RGB = np.array([0.45, 0.25, 0.15])
SSS_PARTS: tuple[str, ...] = ("skin", "nose", "neck", "u_lip", "l_lip")
AO_RAYS = 16
AO_DISTANCE = 0.25  # of the mesh scale (bounding-box diagonal)


@dataclass(frozen=True)
class Effects:
    """Which appearance effects a SynthFaces store renders (recorded per record as ``meta['effects']``)."""

    specular: bool = False
    subsurface: bool = False
    ambient_occlusion: bool = False
    multi_sun: bool = False

    @classmethod
    def resolve(cls, realism: str, overrides: Mapping[str, object] | None = None) -> "Effects":
        """The preset ``realism`` with ``overrides`` (``None`` values keep the preset's)."""
        if realism not in REALISM_PRESETS:
            raise UserError(f"realism={realism!r} is invalid: use one of {', '.join(REALISM_PRESETS)}")
        known = {f.name for f in fields(cls)}
        values = dict(REALISM_PRESETS[realism])
        for k, v in dict(overrides or {}).items():
            if k not in known:
                raise UserError(f"effects.{k} is not an effect: use {', '.join(sorted(known))}")
            if v is None:
                continue
            if not isinstance(v, (bool, np.bool_)):
                raise UserError(f"effects.{k}={v!r} is invalid: use true or false")
            values[k] = bool(v)
        return cls(**values)

    @property
    def any(self) -> bool:
        return any(asdict(self).values())

    def as_dict(self) -> dict[str, bool]:
        return asdict(self)


def wrap(ndl: np.ndarray, w) -> np.ndarray:
    """Wrap lighting ``max(0, (n.l + w) / (1 + w))``; a vector ``w`` (e.g. RGB) adds a last axis. ``w = 0``: Lambert."""
    ndl, w = np.asarray(ndl, dtype=np.float64), np.asarray(w, dtype=np.float64)
    if w.ndim:
        ndl = ndl[..., None]
    return np.maximum((ndl + w) / (1 + w), 0.0)


def blinn_phong(normal: np.ndarray, light_dir, exponent, view=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Blinn-Phong specular factor ``(s + 8) / 8 (n . h)^s max(0, n . l)`` per normal ``(..., 3)``;
    ``exponent`` broadcasts against the normals' leading shape."""
    d = np.asarray(light_dir, dtype=np.float64)
    h = d + np.asarray(view, dtype=np.float64)
    h /= max(np.linalg.norm(h), 1e-12)
    n = np.asarray(normal, dtype=np.float64)
    s = np.asarray(exponent, dtype=np.float64)
    ndh = np.maximum(n @ h, 0.0)
    return (s + 8) / 8 * ndh**s * np.maximum(n @ d, 0.0)


def specular_maps(label: np.ndarray, points: np.ndarray, hit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ``(k_s, s)`` maps ``(H, W)`` from the part labels; the forehead is oily (module doc)."""
    ks = np.zeros(label.shape)
    s = np.ones(label.shape)
    for part, (k, e) in SPECULAR_PARTS.items():
        m = label == PART_INDEX[part]
        ks[m], s[m] = k, e
    brows = np.isin(label, [PART_INDEX["l_brow"], PART_INDEX["r_brow"]]) & hit
    if brows.any():
        forehead = (label == PART_INDEX["skin"]) & hit & (points[..., 1] > points[..., 1][brows].mean())
        ks[forehead] *= FOREHEAD_GAIN
        s[forehead] = SPECULAR_PARTS["nose"][1]
    return ks * hit, s


def sss_mask(label: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Bool ``(H, W)``: pixels where the subsurface (wrap) model applies."""
    return np.isin(label, [PART_INDEX[p] for p in SSS_PARTS]) & hit
