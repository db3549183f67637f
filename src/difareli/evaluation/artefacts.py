"""What a relit photo does to the photo, measured without a model: seams, blotches, brightness and cast shadows.

Every score reads the Rec. 709 luminance ``Y`` (in [0, 1]) of uint8 images of one size and, where it compares a
relight with the photo it came from, the log ratio ``r = log((Y(image) + EPS) / (Y(photo) + EPS))``: the images are
linear, so a relight is a gain and ``r`` its log (a relight that returns the photo has ``r = 0`` everywhere). ``EPS``
is the composite's own floor (:class:`difareli.relight.composite.Compositor`'s ``eps``), so black pixels do not blow
the ratio up. Each score is computed the same way on a ground truth under the target light (where there is one): its
own seam and blotch are what a perfect relight scores, the bound a relight is judged against.

- :func:`seam_score`: the jump of ``r`` across the paste boundary.
- :func:`blotch_score`: the high-frequency energy of ``r`` inside the face, away from cast-shadow edges.
- :func:`luminance_change`: how much brighter (> 0) or darker the face became, in log units.
- :func:`cast_shadow_response`: how much of the darkening a target cast shadow predicts the relight shows.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from difareli.errors import UserError
from difareli.lighting import sh
from difareli.render.retarget import map_direction
from difareli.utils.imageops import luminance

#: The log ratio's floor (luminance units): the composite's ``eps``, 4 of 255 levels.
EPS = 4.0 / 255.0
#: A target shadow must cover at least this share of the face (and leave as much lit) to be scored.
MIN_SHADOW_SHARE = 0.03
#: ... and predict at least this darkening (luminance, 2.5 of 255 levels): a ratio over less is noise.
MIN_PREDICTED = 0.01


def _y(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[-1] != 3:
        raise UserError(f"artefact scores take HxWx3 images, got shape {a.shape}")
    return luminance(a.astype(np.float64) / 255.0)


def log_ratio(image: np.ndarray, photo: np.ndarray, eps: float = EPS) -> np.ndarray:
    """``log((Y(image) + eps) / (Y(photo) + eps))`` per pixel (HxW float64)."""
    if np.shape(image) != np.shape(photo):
        raise UserError(f"artefact scores compare images of one size, got {np.shape(image)} and {np.shape(photo)}")
    return np.log((_y(image) + eps) / (_y(photo) + eps))


def _bands(paste: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(boundary pixels of ``paste``, the band of ``width`` px just inside it, the band just outside it)."""
    inner = paste & ~ndimage.binary_erosion(paste, iterations=width, border_value=1)
    outer = ndimage.binary_dilation(paste, iterations=width) & ~paste
    edge = paste & ~ndimage.binary_erosion(paste, border_value=1)
    return edge & ndimage.binary_dilation(outer), inner, outer


def seam_score(image: np.ndarray, photo: np.ndarray, paste: np.ndarray, width: int = 3, eps: float = EPS) -> float:
    """The seam of ``image`` pasted into ``photo`` over the region ``paste`` (bool HxW): at every boundary pixel of
    ``paste``, the mean of the log ratio ``r`` over the ``width``-px band just inside the boundary minus its mean
    over the band just outside, both within a window of ``2 width + 1`` px around the pixel; the score is the mean
    of ``|inside - outside|`` over the boundary (log units: 0.1 is a 10% step in brightness). Boundary pixels on the
    image's edge, with nothing outside them, do not count; NaN when none is left."""
    paste = np.asarray(paste, bool)
    if paste.shape != np.shape(photo)[:2]:
        raise UserError(f"seam_score: the paste region is {paste.shape}, the photo {np.shape(photo)[:2]}")
    if width < 1:
        raise UserError(f"seam_score: width={width}; give a band of at least 1 px")
    r = log_ratio(image, photo, eps)
    edge, inner, outer = _bands(paste, int(width))
    size = 2 * int(width) + 1
    means = []
    for band in (inner, outer):
        n = ndimage.uniform_filter(band.astype(np.float64), size, mode="constant")
        s = ndimage.uniform_filter(np.where(band, r, 0.0), size, mode="constant")
        means.append((s, n))
    (si, ni), (so, no) = means
    ok = edge & (ni > 0) & (no > 0)
    if not ok.any():
        return math.nan
    jump = si[ok] / ni[ok] - so[ok] / no[ok]
    return float(np.abs(jump).mean())


def shadow_edges(masks, width: int) -> np.ndarray:
    """The pixels within ``width`` px of an edge of any of the binary shadow ``masks`` (bool HxW each), where a
    relight's ratio may rightly change fast (a cast shadow's own edge)."""
    masks = [np.asarray(m, bool) for m in masks]
    out = np.zeros(masks[0].shape, bool)
    for m in masks:
        if m.any() and not m.all():
            out |= ndimage.binary_dilation(m, iterations=width) & ~ndimage.binary_erosion(m, iterations=width,
                                                                                             border_value=1)
    return out


def blotch_score(image: np.ndarray, photo: np.ndarray, face: np.ndarray, sigma: float,
                 exclude: np.ndarray | None = None, eps: float = EPS) -> float:
    """The blotchiness of ``image`` against ``photo`` on ``face`` (bool HxW): the root mean square of the log ratio
    ``r`` less its Gaussian blur of ``sigma`` px (the blur normalised over the face, so pixels off the face never
    enter), over the face eroded by ``3 sigma`` (where the blur's window lies inside the face) less ``exclude``
    (e.g. :func:`shadow_edges`). A smooth change of light (a linear ``r``) scores 0; blotches smaller than about
    ``sigma`` score their amplitude. NaN when no pixel is left."""
    face = np.asarray(face, bool)
    if face.shape != np.shape(photo)[:2]:
        raise UserError(f"blotch_score: the face region is {face.shape}, the photo {np.shape(photo)[:2]}")
    if not sigma > 0:
        raise UserError(f"blotch_score: sigma={sigma}; give a blur of more than 0 px")
    r = log_ratio(image, photo, eps)
    weight = ndimage.gaussian_filter(face.astype(np.float64), sigma, mode="constant", truncate=3.0)
    blur = ndimage.gaussian_filter(np.where(face, r, 0.0), sigma, mode="constant", truncate=3.0)
    high = r - blur / np.maximum(weight, 1e-12)
    where = ndimage.binary_erosion(face, iterations=int(math.ceil(3 * sigma)), border_value=0)
    if exclude is not None:
        where &= ~np.asarray(exclude, bool)
    return float(np.sqrt(np.mean(high[where] ** 2))) if where.any() else math.nan


def luminance_change(image: np.ndarray, photo: np.ndarray, region: np.ndarray) -> float:
    """``log(mean Y(image) / mean Y(photo))`` over ``region`` (bool HxW): > 0 brighter, < 0 darker (-0.69: half
    as bright). NaN for an empty region or a black photo there."""
    region = np.asarray(region, bool)
    if not region.any():
        return math.nan
    a, b = float(_y(image)[region].mean()), float(_y(photo)[region].mean())
    return math.log(a / b) if a > 0 and b > 0 else math.nan


def key_sun_share(light: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """The share of each pixel's irradiance under the SH ``light`` (9x3) that its key sun gives (HxW in [0, 1];
    0 where ``normal`` holds no normal): what a cast shadow of that light takes away. The key sun lies along the
    direction a target shadow map is marched toward (:func:`~difareli.render.retarget.map_direction`), with the
    RGB strength that gives the light's band 1 along it (the directional part of the light; the rest is ambient);
    its term is ``strength * max(0, n.d)``."""
    light = np.asarray(light, np.float64)
    n = np.asarray(normal, np.float64)
    d = map_direction(light)
    unit = sh.directional_light(d, 1.0)[1:4, 0]
    strength = np.maximum(light[1:4].T @ unit / float(unit @ unit), 0.0)  # (3,) RGB
    known = np.linalg.norm(n, axis=-1) > 0.5
    total = luminance(sh.irradiance(light, n))
    sun = luminance(np.maximum(n @ d, 0.0)[..., None] * strength)
    share = np.where(total > 1e-9, sun / np.maximum(total, 1e-9), 1.0)
    return np.where(known, np.clip(share, 0.0, 1.0), 0.0)


def cast_shadow_response(relit: np.ndarray, unshadowed: np.ndarray, face: np.ndarray, m: np.ndarray,
                         share: np.ndarray, ring: int = 3, min_share: float = MIN_SHADOW_SHARE,
                         min_predicted: float = MIN_PREDICTED) -> float:
    """How much of a target cast shadow a relight shows: the darkening of the target map ``m`` in ``relit``
    (the mean luminance of the face pixels within ``ring`` px around ``m`` minus its mean inside ``m``: a cast
    shadow is a local drop, and a ring keeps a change of shading across the whole face out) beyond the same
    darkening in ``unshadowed`` (the same face under the target light without cast shadows, e.g. the Lambertian
    ratio relight: its own shading differs inside and around ``m``), over the darkening the cast shadow predicts:
    the mean over ``m`` of ``Y(unshadowed) * share`` (``share``: :func:`key_sun_share`). 1: the shadow the light
    casts; 0: none. NaN unless ``m`` covers between ``min_share`` and ``1 - min_share`` of the face and predicts
    a darkening of at least ``min_predicted``."""
    face, m = np.asarray(face, bool), np.asarray(m, bool) & np.asarray(face, bool)
    if not face.any():
        return math.nan
    cover = m.sum() / face.sum()
    around = ndimage.binary_dilation(m, iterations=int(ring)) & face & ~m
    if not min_share <= cover <= 1.0 - min_share or not around.any():
        return math.nan
    y, y0 = _y(relit), _y(unshadowed)
    predicted = float((y0 * np.asarray(share, np.float64))[m].mean())
    if predicted < min_predicted:
        return math.nan
    dark = lambda v: float(v[around].mean() - v[m].mean())  # noqa: E731
    return (dark(y) - dark(y0)) / predicted
