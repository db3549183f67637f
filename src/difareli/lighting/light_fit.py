"""The SH light of a face from its image alone, as a user gets it: one albedo prior, two fitters named for
what their inputs allow.

- :class:`LightFit` fits a **record** (its stored normals and face parsing): the benchmark's target and source
  lights, the Lambertian ratio image, and SynthFaces' estimated ``light`` (so the two agree by construction).
  Its robust pass drops only pixels far *darker* than the fit: cast shadows, which 9 SH terms cannot explain.
- :class:`difareli.estimators.light.SkinSHLight` fits a **photo** inside ``difareli-preprocess``, where normals
  come from a fitted face surface and the skin from a parser: it erodes the skin, keeps pixels facing the camera
  and clips residuals on *both* sides (specular highlights and stray hair as well as shadows), with a small
  ridge, because estimated geometry is rougher than a record's.

Both use :func:`synthfaces_mean_skin_albedo` as the albedo prior. SynthFaces images are linear
(``image = albedo * irradiance``, no gamma), so the fit is the image formation model itself. A single image
cannot separate albedo from light intensity: the fitted light is the true one times ``true albedo / prior``. The
default prior is SynthFaces' population-mean skin albedo (the mean of its skin-tone model over the uniform tone
distribution), the analogue of DECA's mean albedo: unbiased over the data set, though a very light or dark
subject still gets a proportionally too dark or bright light (paper Sec. VI).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from difareli.lighting import sh
from difareli.lighting.albedo import synthfaces_mean_skin_albedo
from difareli.data.encodings import PART_INDEX, known_normals
from difareli.errors import UserError


def face_normals(arrays: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(normals float64 HxWx3, bool mask of pixels with a stored unit normal)."""
    n = np.asarray(arrays["normal"], dtype=np.float64)
    return n, known_normals(n)

#: A pixel darker than the fit by more than this many robust sigmas is a cast shadow the SH cannot explain: the
#: robust refit drops it (and ``render.sun_fit`` reads it as the shadow's evidence).
SHADOW_SIGMAS = 2.5


def robust_sigma(r: np.ndarray) -> float:
    """The standard deviation of ``r`` estimated from its median absolute deviation (1.4826 x MAD: exact for a
    normal distribution, blind to the cast-shadow outliers)."""
    r = np.asarray(r, dtype=np.float64)
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


#: Pixels a 9-term SH light needs at the least (one per coefficient); a bound below it cannot be suggested.
MIN_FIT_PIXELS = 9


@dataclass(frozen=True)
class LightFit:
    """Estimate a record's SH light from its image alone (plus its normals and face parsing).

    Pixels used: the face mask, where a normal is stored, restricted to ``parts`` of the ``masks`` parsing
    (skin and nose: brows, eyes and lips have other albedos than the prior), and neither clipped nor black
    (the clip breaks the linear model). ``robust_iters`` refits after dropping pixels far darker than the fit
    (residual below ``-2.5`` robust sigmas): cast shadows, which a 9-term SH cannot explain.
    """

    albedo: tuple[float, float, float] | float | None = None  # None: SynthFaces' mean skin albedo
    parts: tuple[str, ...] = ("skin", "nose")
    robust_iters: int = 2
    min_pixels: int = 30

    ENCODINGS = ("image", "normal", "face_mask", "masks")

    def prior(self) -> np.ndarray:
        a = synthfaces_mean_skin_albedo() if self.albedo is None else np.broadcast_to(
            np.asarray(self.albedo, dtype=np.float64), (3,))
        return np.asarray(a, dtype=np.float64)

    def region(self, arrays: Mapping[str, np.ndarray]) -> np.ndarray:
        """The pixels (bool HxW) the fit uses: the face with a stored normal, in ``parts``, neither clipped nor
        black."""
        img = np.asarray(arrays["image"], dtype=np.float64) / 255.0
        m = face_normals(arrays)[1] & np.asarray(arrays["face_mask"], dtype=bool)
        if self.parts and "masks" in arrays:
            m &= np.isin(np.asarray(arrays["masks"]), [PART_INDEX[p] for p in self.parts])
        return m & (img.max(-1) < 254.5 / 255) & (img.min(-1) > 0.5 / 255)

    def pixels(self, arrays: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(intensities in [0, 1], normals), both (N, 3), of the pixels the fit uses (:meth:`region`)."""
        img = np.asarray(arrays["image"], dtype=np.float64) / 255.0
        normal = face_normals(arrays)[0]
        m = self.region(arrays)
        if m.sum() < self.min_pixels:
            raise UserError(f"light fit: only {int(m.sum())} usable face pixels (need {self.min_pixels})")
        return img[m], normal[m]

    def __call__(self, arrays: Mapping[str, np.ndarray]) -> np.ndarray:
        y, n = self.pixels(arrays)
        albedo = self.prior()
        w = np.ones(len(y))
        light = sh.fit(y, n, albedo, weights=w)
        for _ in range(self.robust_iters):
            r = (y - albedo * sh.irradiance(light, n)).mean(-1)
            sigma = robust_sigma(r)
            keep = r >= -SHADOW_SIGMAS * max(sigma, 1e-4)
            if keep.sum() < 9 or keep.all():
                break
            light = sh.fit(y, n, albedo, weights=keep.astype(np.float64))
        return light

    def from_store(self, store, record_id: str) -> np.ndarray:
        """The fit of one record of an :class:`~difareli.data.store.EncodingStore`."""
        names = [e for e in self.ENCODINGS if e != "masks" or store.available("masks")]
        arrays = store.read(record_id, names)
        have = int(self.region(arrays).sum())
        if have < self.min_pixels:  # said with the record and the fix, not as a bare count
            lower = f", or lower the bound: light_fit.min_pixels={have}" if have >= MIN_FIT_PIXELS else ""
            raise UserError(
                f"store {store.root}, record {record_id}: its image has {have} face pixels the light fit can use "
                f"(skin and nose, neither clipped nor black), under light_fit.min_pixels={self.min_pixels}; a "
                f"store at a larger resolution gives it more (this one is {int(store.dims.get('H', 0))} px){lower}")
        return self(arrays)


def light_fit_from_config(cfg: Mapping[str, Any] | None) -> LightFit:
    """A :class:`LightFit` from the ``light_fit`` config block (``albedo: null | number | [r, g, b]``)."""
    cfg = dict(cfg or {})
    albedo = cfg.get("albedo")
    if albedo is not None and not isinstance(albedo, (int, float)):
        albedo = tuple(float(x) for x in albedo)
    parts: Sequence[str] = tuple(cfg.get("parts") or ())
    unknown = [p for p in parts if p not in PART_INDEX]
    if unknown:
        raise UserError(f"light_fit.parts: unknown parts {unknown}; choose from {list(PART_INDEX)}")
    return LightFit(albedo=albedo, parts=tuple(parts), robust_iters=int(cfg.get("robust_iters", 2)),
                    min_pixels=int(cfg.get("min_pixels", 30)))
