"""A light's key sun found from the cast shadows of the image it was fitted to.

An SH light fitted to a face (``lighting.light_fit.LightFit``) says how bright each normal is; where its sun is,
it says only roughly: the radiance peak of a fitted light lies 20-33 degrees (median) from the key sun on
SynthFaces, and a cast-shadow map marched toward it matches the real shadows at IoU 0.14 (docs/shadow_maps.md,
section 2). The image itself shows where the sun is: its cast shadows are the pixels the SH cannot explain,
far darker than the fit predicts (the same residual ``LightFit``'s robust rule drops). :func:`fit_sun` marches
the depth toward candidate directions around the radiance peak and keeps the one whose cast shadow covers those
pixels best, a small cost per degree keeping it near the peak when the evidence is weak; with too little
evidence (no visible cast shadow) the peak stays. The map a relight marches toward that sun is the target's
shadow map (``relight.targets``): the light's own direction, known from the photo whose light it is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from difareli.lighting import sh
from difareli.lighting.light_fit import SHADOW_SIGMAS, LightFit, face_normals, robust_sigma
from difareli.lighting.suns import fibonacci_sphere, sun_direction
from difareli.render.camera import OrthoCamera
from difareli.render.screen_shadow import march_shadows

#: The search, chosen on the 38 sunlit val records of an unseen-seed v3 store (``scripts/sun_fit_sweep.py``,
#: docs/shadow_maps.md section 2): candidates within ``CONE_DEG`` of the radiance peak, each scored by the IoU of
#: its cast map with the evidence less ``ANGLE_COST`` per 90 degrees from the peak.
CONE_DEG = 40.0
ANGLE_COST = 0.3
#: Fewer evidence pixels than this (at 64 px: a 3x3 patch) is no visible cast shadow: the peak stays.
MIN_EVIDENCE = 10
_CANDIDATES = fibonacci_sphere(4000)  # about 3.2 degrees apart

#: The encodings :func:`fit_sun` reads of the lit image's record (``masks`` where there are any).
ENCODINGS = ("image", "normal", "depth", "cam", "face_mask", "masks")

#: Where a fitted light's cast-shadow map is marched (the ``target_sun`` setting of the benchmark, the relight and
#: the video): ``shadows``, toward the key sun found from the cast shadows of the image the light was fitted to
#: (:func:`key_sun`); ``peak``, toward the light's radiance peak.
TARGET_SUNS = ("shadows", "peak")
#: Where a target map is marched without a key sun (none found, or none sought).
PEAK_NOTE = "marched toward the light's radiance peak"


@dataclass(frozen=True)
class SunFit:
    """``direction`` (3,) unit, toward the key sun; ``peak`` the light's radiance peak it started from;
    ``evidence`` the number of unexplained dark pixels; ``iou`` of the chosen direction's cast map with them."""

    direction: np.ndarray
    peak: np.ndarray
    evidence: int
    iou: float

    @property
    def moved_deg(self) -> float:
        """Degrees between the found sun and the radiance peak."""
        return float(np.degrees(np.arccos(np.clip(self.direction @ self.peak, -1.0, 1.0))))

    @property
    def note(self) -> str:
        """Where a target shadow map marched toward this fit goes, for console lines and summaries (no fit at
        all: :data:`PEAK_NOTE`)."""
        if self.evidence < MIN_EVIDENCE:
            return (f"{PEAK_NOTE} (the image shows {self.evidence} px of cast shadow, fewer than the "
                    f"{MIN_EVIDENCE} its key sun is found from)")
        return (f"marched toward the key sun found from the image's cast shadows ({self.evidence} px; "
                f"{self.moved_deg:.1f} degrees from the radiance peak, map IoU {self.iou:.2f})")


def shadow_evidence(arrays: Mapping[str, np.ndarray], light: np.ndarray, fit: LightFit | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``(evidence, region)``, bool HxW: of the light fit's pixels (``region``: ``LightFit.region``, skin and nose
    with a stored normal), those whose intensity lies more than ``SHADOW_SIGMAS`` robust sigmas below the median
    residual of ``albedo prior * irradiance(light)``: what a 9-term SH cannot explain, a cast shadow."""
    fit = fit or LightFit()
    region = fit.region(arrays)
    if not region.any():
        return region, region
    normal = face_normals(arrays)[0]
    img = np.asarray(arrays["image"], np.float64) / 255.0
    r = (img - fit.prior() * sh.irradiance(np.asarray(light, np.float64), normal)).mean(-1)
    cut = float(np.median(r[region])) - SHADOW_SIGMAS * max(robust_sigma(r[region]), 1e-4)
    return region & (r < cut), region


def fit_sun(arrays: Mapping[str, np.ndarray], light: np.ndarray, *, cone_deg: float = CONE_DEG,
            angle_cost: float = ANGLE_COST, fit: LightFit | None = None) -> SunFit:
    """The key sun of ``light`` (the SH fitted to ``arrays``' image), found from the image's cast shadows on its
    ``depth`` (module doc); the radiance peak when fewer than :data:`MIN_EVIDENCE` pixels show a cast shadow."""
    peak = sun_direction(light)
    evidence, region = shadow_evidence(arrays, light, fit)
    count = int(evidence.sum())
    if count < MIN_EVIDENCE:
        return SunFit(peak, peak, count, float("nan"))
    cos = _CANDIDATES @ peak
    cands = np.concatenate([peak[None], _CANDIDATES[cos > np.cos(np.radians(cone_deg))]])
    depth = np.asarray(arrays["depth"], np.float64)
    cam = OrthoCamera(*np.asarray(arrays["cam"], np.float64).tolist())
    maps = march_shadows(depth, depth != 0, cam, cands, normal=np.asarray(arrays["normal"], np.float64))
    maps &= region  # scored where evidence can be
    iou = (maps & evidence).sum((1, 2)) / np.maximum((maps | evidence).sum((1, 2)), 1)
    degrees = np.degrees(np.arccos(np.clip(cands @ peak, -1.0, 1.0)))
    best = int(np.argmax(iou - angle_cost * degrees / 90.0))  # ties keep the first: the peak
    return SunFit(cands[best], peak, count, float(iou[best]))


def key_sun(arrays: Mapping[str, np.ndarray], light: np.ndarray, fit: LightFit | None = None) -> SunFit | None:
    """:func:`fit_sun` of ``light`` on the image it was fitted to where ``arrays`` hold what it reads
    (:data:`ENCODINGS`, ``masks`` optional), else None: the light's radiance peak stays its sun."""
    if any(k not in arrays for k in ENCODINGS if k != "masks"):
        return None
    return fit_sun(arrays, light, fit=fit)


def record_sun(store, record_id: str, light: np.ndarray, fit: LightFit | None = None) -> SunFit | None:
    """:func:`key_sun` of ``light`` on ``store``'s record ``record_id`` (the image it was fitted to)."""
    return key_sun(store.read(record_id, [k for k in ENCODINGS if store.available(k)]), light, fit=fit)
