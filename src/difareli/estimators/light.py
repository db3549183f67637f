"""SH lighting from skin pixels (``sh.fit``) and the shading reference.

Pixel values are used as they are, ``rgb / 255`` with no gamma, because SynthFaces forms its images as
``albedo * irradiance`` without gamma (``synth/subject.py``, like DECA's photometric fit): a light estimated
here is on the scale of the SynthFaces lights the model was trained with.

Albedo-light ambiguity (paper Sec. VI): ``image = a * E(l)`` cannot separate a constant albedo ``a`` from
the light; albedo ``k a`` with light ``l / k`` explains the photo equally well. We fix ``a`` to a prior:
by default the mean SynthFaces skin albedo (the Monk-scale tones times ``SKIN_ALBEDO_SCALE``, averaged over
the uniform tone distribution), so dark skin yields a dimmer light and light skin a brighter one, exactly
the bias the paper discusses. A float (or RGB triple) overrides it.

Skin pixels: the ``skin`` part eroded by ``erode`` of the image size, on the rendered face surface, facing
the camera (``n_z > min_nz``), not saturated and not black; one robust pass then drops pixels whose
luminance residual exceeds ``clip_mads`` MADs (specular highlights, cast shadows, stray hair).

A grey photo (:func:`is_grey`: R, G and B within ``GREY_TOLERANCE`` levels on all but 1% of the crop) carries no
colour, so its light is fitted on the luminance with the prior's luminance as albedo and copied to R, G and B: a
grey light, never a tint invented by the colour prior (fitting the grey pixels per channel against a skin-coloured
albedo gives a bluish light).

:func:`light_direction` / :func:`describe_light` say where a light comes from (console lines, the report, the
previews): the dominant direction of band 1 (``sh.dominant_direction``) as yaw = atan2(x, z) and pitch = asin(y)
in degrees, camera space (x right, y up, z toward the viewer). Positive yaw: from the image's right, which is the
subject's left; positive pitch: from above.
"""

from __future__ import annotations

import numpy as np

from difareli.lighting import sh
from difareli.lighting.albedo import synthfaces_mean_skin_albedo
from difareli.utils.imageops import LUMA

from .loading import BadInput

#: Levels (of 255) by which the channels of a grey photo's pixel may differ (JPEG chroma noise).
GREY_TOLERANCE = 4
#: Below this many degrees a yaw / pitch counts as frontal / level in the words of :func:`describe_direction`.
SIDE_DEGREES = 15.0


def is_grey(image: np.ndarray, tolerance: int = GREY_TOLERANCE, share: float = 0.01) -> bool:
    """Whether a uint8 RGB image is grey: its channels differ by more than ``tolerance`` levels on at most
    ``share`` of the pixels."""
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[-1] != 3:
        return False
    a = a if a.dtype == np.uint8 else a.astype(np.int16)  # uint8: max - min cannot wrap
    # Channel by channel: numpy's max over a last axis of 3 is ~10x slower than two elementwise maxima.
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    spread = np.maximum(np.maximum(r, g), b) - np.minimum(np.minimum(r, g), b)
    return bool(np.mean(spread > tolerance) <= share)


def light_direction(light: np.ndarray) -> dict:
    """Where ``light`` (9x3) comes from: ``{"yaw_deg", "pitch_deg", "direction", "from"}`` (see the module)."""
    d = sh.dominant_direction(np.asarray(light, dtype=np.float64))
    yaw = float(np.degrees(np.arctan2(d[0], d[2])))
    pitch = float(np.degrees(np.arcsin(np.clip(d[1], -1.0, 1.0))))
    return {"yaw_deg": round(yaw, 1), "pitch_deg": round(pitch, 1), "direction": [round(float(v), 4) for v in d],
            "from": describe_direction(yaw, pitch)}


def describe_direction(yaw: float, pitch: float) -> str:
    """Words for a light direction: ``"the image's upper right (the subject's left)"``, ``"the front"``..."""
    vert = "" if abs(pitch) < SIDE_DEGREES else ("upper" if pitch > 0 else "lower")
    side = "" if abs(yaw) < SIDE_DEGREES or abs(yaw) > 180 - SIDE_DEGREES else ("right" if yaw > 0 else "left")
    behind = " behind" if abs(yaw) > 90 else ""
    if side:
        where = (f"the image's {vert + ' ' if vert else ''}{side}{behind} "
                 f"(the subject's {'left' if yaw > 0 else 'right'})")
    elif vert:
        where = ("above" if vert == "upper" else "below") + (", behind" if behind else ", in front")
    else:
        where = "behind" if behind else "the front"
    return where


def describe_light(light: np.ndarray) -> str:
    """One phrase: ``"yaw +34 deg, pitch +21 deg: from the image's upper right (the subject's left)"``."""
    d = light_direction(light)
    return f"yaw {d['yaw_deg']:+.0f} deg, pitch {d['pitch_deg']:+.0f} deg: from {d['from']}"


class SkinSHLight:
    """Estimator: ``light`` (9x3) fitted on a photo's skin, and the shading reference ``shading`` (how it differs
    from a record's :class:`difareli.lighting.light_fit.LightFit`: see that module)."""

    provides = ("light", "shading", "fit_pixels", "albedo_prior")
    requires = ("image", "gbuffer", "skin")

    def __init__(self, albedo="synthfaces", erode: float = 0.015, min_nz: float = 0.15, saturated: float = 0.98,
                 dark: float = 0.02, clip_mads: float = 3.0, ridge: float = 1e-3, min_pixels: int = 100):
        self.albedo = synthfaces_mean_skin_albedo() if albedo == "synthfaces" else np.broadcast_to(
            np.asarray(albedo, dtype=np.float64), (3,)).copy()
        self.erode, self.min_nz, self.saturated, self.dark = erode, min_nz, saturated, dark
        self.clip_mads, self.ridge, self.min_pixels = clip_mads, ridge, min_pixels

    def skin_pixels(self, image: np.ndarray, gbuffer, skin: np.ndarray) -> np.ndarray:
        """Bool mask of pixels the fit may use (before the robust pass)."""
        import cv2  # ships with mediapipe; ~20x faster than scipy's binary_erosion for a disk

        r = max(1, int(round(self.erode * image.shape[0])))
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        m = cv2.erode(skin.astype(np.uint8), disk, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
        m &= gbuffer.hit & (gbuffer.normal[..., 2] > self.min_nz)
        # The colour tests on those pixels only: the whole crop in float64 cost more than the rest of the stage.
        idx = np.flatnonzero(m)
        rgb = image.reshape(-1, 3)[idx].astype(np.float64) / 255.0
        ok = (rgb.max(-1) < self.saturated) & (rgb @ LUMA > self.dark)
        out = np.zeros(m.size, dtype=bool)
        out[idx[ok]] = True
        return out.reshape(m.shape)

    def fit(self, image: np.ndarray, normal: np.ndarray, mask: np.ndarray, grey: bool | None = None
            ) -> tuple[np.ndarray, np.ndarray, dict]:
        """Robust fit on ``mask``; returns (light, mask of pixels kept, stats). ``grey`` (default: :func:`is_grey`
        of ``image``): fit on the luminance, with the prior's luminance as albedo, and copy it to R, G, B."""
        grey = is_grey(image) if grey is None else bool(grey)
        y = image[mask].astype(np.float64) / 255.0
        n = normal[mask].astype(np.float64)
        albedo = self.albedo
        if grey:
            y = np.repeat((y @ LUMA)[:, None], 3, axis=1)
            albedo = np.full(3, float(self.albedo @ LUMA))
        if len(y) < self.min_pixels:
            raise BadInput(f"too few usable skin pixels for the light fit ({len(y)} < {self.min_pixels})")
        basis = sh.sh_basis(n)  # (N, 9) once: sh.irradiance(light, n) is basis @ light
        keep = np.ones(len(y), dtype=bool)
        for _ in range(2):
            light = sh.fit(y[keep], n[keep], albedo, ridge=self.ridge * keep.sum(), basis=basis[keep])
            if grey:  # one light for the three channels, exactly
                light = np.repeat(light[:, :1], 3, axis=1)
            irr = basis @ light
            res = (y - albedo * irr) @ LUMA
            dev = np.abs(res - np.median(res))
            mad = 1.4826 * np.median(dev) + 1e-6
            new = dev < self.clip_mads * mad
            if new.sum() < self.min_pixels or np.array_equal(new, keep):
                break
            keep = new
        pred = albedo * irr[keep]
        obs = y[keep]
        lum_p, lum_o = pred @ LUMA, obs @ LUMA
        stats = {"pixels": int(keep.sum()), "rmse": float(np.sqrt(((pred - obs) ** 2).mean())),
                 "rel_rmse": float(np.sqrt(((lum_p - lum_o) ** 2).mean()) / max(lum_o.mean(), 1e-6)),
                 "corr": float(np.corrcoef(lum_p, lum_o)[0, 1]) if lum_o.std() > 0 else 0.0, "grey": grey}
        used = np.zeros(mask.size, dtype=bool)
        used[np.flatnonzero(mask)[keep]] = True
        used = used.reshape(mask.shape)
        return light.astype(np.float32), used, stats

    def __call__(self, ctx: dict, needed: set[str]) -> dict:
        gb = ctx["gbuffer"]
        mask = self.skin_pixels(ctx["image"], gb, ctx["skin"])
        grey = is_grey(ctx["image"])
        light, used, stats = self.fit(ctx["image"], gb.normal, mask, grey=grey)
        stats["direction"] = light_direction(light)
        # Only the surface's pixels: the rest is 0 (shading_reference's mask), and the face is ~25% of the crop.
        shading = np.zeros(gb.normal.shape, dtype=np.float32)
        shading[gb.hit] = sh.shading_reference(light, gb.normal[gb.hit])
        notes = ["grey photo: light fitted on the luminance, equal in R, G and B"] if grey else []
        return {"light": light, "shading": shading, "fit_pixels": used, "light_fit": stats, "notes": notes,
                "albedo_prior": np.full(3, float(self.albedo @ LUMA)) if grey else self.albedo}
