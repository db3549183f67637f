"""A DiFaReli's response to its shadow scalar c, turned into a binary shadow map and judged (paper Sec. IV-A).

The difference of one record is ``d = Y(relit at c_min) - Y(relit at c_max)`` (Rec. 709 luminance in [0, 1]):
positive where the stronger shadow darkened the face. Raising c also changes the face's overall brightness (a
DiFaReli trained on SynthFaces brightens the lit skin as c grows: the light removed by the shadow is given back
elsewhere), so the raw difference mixes a global shift with the cast shadow. Here:

1. **centre** (``centre=median``, the default; ``mean``; ``none`` = the authors' recipe): each record's face
   median (or mean) of ``d`` is subtracted first, so what remains is the *spatial* response;
2. **threshold**: ``relative`` (the default) cuts at ``relative`` (0.15) times the 99th percentile of the centred face
   differences of the records judged (the response's own scale: the authors' fixed 0.05 belongs to a 256-px FFHQ
   model and does not transfer to a 64-px one); a number is a fixed cut (0.05: theirs); ``otsu`` Otsu's cut,
   refused on a histogram without two separated modes;
3. the map: the cut, a median filter (``median=auto``: theirs, 5 px at 256 scaled), restricted to the mesh and
   the kept parts, times the record's normalised c (:func:`finish_map`).

A DiFaReli is **judged by the spatial contrast of its response**, not by the sign balance of its raw differences:
``contrast`` is how much more its candidate shadow pixels (``d > cut``) darken than the rest of the face (mean
centred difference inside minus outside, luminance units), and ``coherence`` how much more often a candidate's 8
neighbours are candidates than chance would make them (a cast shadow is a region or, at 64 px, a thin line under a
brim or the hairline; sampling noise is speckle at any density. A 3x3 median would erase the thin lines too: it kept
23% of the candidates of a DiFaReli whose candidates were 0.14 darker than the rest of the face). Too little contrast
(``min_contrast``) or too little coherence (``min_coherence``) is refused, naming what was measured.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from difareli import errors
from difareli.data import encodings
from difareli.utils.imageops import median_mask

#: The authors' recipe: threshold on the grey-level difference, median size at 256 px.
RECIPE_THRESHOLD = 0.05
RECIPE_MEDIAN_256 = 5
#: ``threshold=relative``: the cut as this share of the 99th percentile of the centred face differences. Chosen on
#: the shadowed val records of a v3 store with the shipped DiFaReli (IoU 0.122 at 0.15 against 0.099 / 0.080 / 0.058
#: at 0.25 / 0.35 / 0.5 and 0.083 for the authors' fixed 0.05; scripts/difference_map_rules.py); test: 0.156.
RELATIVE = 0.15
#: The defaults of the judge: candidates at least this much darker than the rest of the face (luminance in [0, 1]),
#: and neighbours that are candidates at least this much more often than chance (:func:`measure`).
MIN_CONTRAST = 0.01
MIN_COHERENCE = 0.1
CENTRES = ("median", "mean", "none")


def median_size(median, resolution: int) -> int:
    """``median`` as an odd window: ``"auto"`` is the recipe's 5 px at 256 scaled to ``resolution`` (1 at 64)."""
    if median != "auto":
        return int(median)
    return max(1, 2 * int(round((RECIPE_MEDIAN_256 * resolution / 256 - 1) / 2)) + 1)


def check_threshold(threshold) -> str | float:
    """``threshold`` as ``"relative"``, ``"otsu"`` or a float in (0, 1): the grey-level differences lie in [-1, 1]
    and a shadow darkens, so a cut <= 0 marks nearly every pixel (and >= 1 none)."""
    if threshold in ("otsu", "relative"):
        return threshold
    try:
        t = float(threshold)
    except (TypeError, ValueError):
        t = float("nan")
    if not 0.0 < t < 1.0:  # NaN included
        raise errors.UserError(f"threshold={threshold!r} is out of range: it cuts the grey-level difference in [0, 1] "
                               f"and must lie strictly between 0 and 1 (<= 0 marks almost every pixel); use "
                               f"threshold=relative (the default), the recipe's {RECIPE_THRESHOLD}, or otsu")
    return t


def check_centre(centre) -> str:
    """``centre`` as one of :data:`CENTRES`."""
    if centre not in CENTRES:
        raise errors.UserError(f"centre={centre!r} is not a centring rule; choose one of {', '.join(CENTRES)} "
                               "(median: subtract each record's face median of the difference first)")
    return str(centre)


def centred(diff: np.ndarray, on_face: np.ndarray, centre: str) -> np.ndarray:
    """``diff`` less its median (or mean) over ``on_face`` (``none``: unchanged); float64."""
    d = np.asarray(diff, dtype=np.float64)
    if centre == "none" or not on_face.any():
        return d
    return d - (np.median(d[on_face]) if centre == "median" else d[on_face].mean())


def check_two_modes(values: np.ndarray, threshold: float, bins: int = 256, valley: float = 0.5) -> None:
    """Refuse an Otsu cut on a histogram without two separated modes: the emptiest (5-bin smoothed) bin between
    the peaks on either side of ``threshold`` must hold at most ``valley`` of the lower peak."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    hist, edges = np.histogram(v, bins=bins)
    h = np.convolve(hist, np.ones(5) / 5, mode="same")
    k = int(np.clip(np.searchsorted(edges, threshold) - 1, 1, bins - 2))
    lo, hi = int(np.argmax(h[:k])), k + int(np.argmax(h[k:]))
    dip = float(h[lo:hi + 1].min()) if hi > lo else float(h[k])
    lower = float(min(h[lo], h[hi]))
    if lower <= 0 or dip > valley * lower:
        raise errors.UserError(
            f"the differences have one mode, not two: Otsu's cut {threshold:.4f} lies where the histogram still holds "
            f"{dip / max(lower, 1e-12):.0%} of its lower peak (peaks at {edges[lo]:.4f} and {edges[hi]:.4f}), so it "
            f"would mark noise; use threshold=relative (the default) or a DiFaReli trained longer")


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of ``values``: the bin edge maximising the between-class variance (values > t: class 1);
    the middle of the maximising edges when several tie (empty bins between two modes)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    v = v[np.isfinite(v)]
    if v.size == 0 or v.max() == v.min():
        raise errors.UserError("Otsu's threshold needs at least two distinct finite values")
    hist, edges = np.histogram(v, bins=bins)
    p = hist / hist.sum()
    centres = (edges[:-1] + edges[1:]) / 2
    w0 = np.cumsum(p)[:-1]                       # class 0 = bins 0..k, threshold at edges[k + 1]
    m = np.cumsum(p * centres)
    mu0 = m[:-1] / np.maximum(w0, 1e-300)
    mu1 = (m[-1] - m[:-1]) / np.maximum(1 - w0, 1e-300)
    between = w0 * (1 - w0) * (mu0 - mu1) ** 2
    # Empty bins between the modes make a plateau of equal maxima: take its middle, not its first edge.
    best = np.flatnonzero(between >= between.max() * (1 - 1e-9))
    return float((edges[1 + best[0]] + edges[1 + best[-1]]) / 2)


def finish_map(diff: np.ndarray, threshold: float, median: int, c: float, hit: np.ndarray | None = None,
               keep: np.ndarray | None = None, c_range=None) -> np.ndarray:
    """Threshold, median-filter, restrict to the mesh and to ``keep`` (the face less the zeroed parts) and scale by
    ``normalise_c(c, c_range)`` -> float32 HxW."""
    binary = np.asarray(diff) > threshold
    if median > 1:
        binary = median_mask(binary, int(median))
    for m in (hit, keep):
        if m is not None:
            binary &= np.asarray(m, bool)
    return (binary * encodings.normalise_c(c, c_range)).astype(np.float32)


@dataclass
class Response:
    """What the judge measured on the centred face differences of some records."""

    threshold: float      # the cut
    rule: str             # how it was chosen
    p99: float            # 99th percentile of the centred face differences (the response's scale)
    contrast: float       # mean difference of the candidates minus that of the rest of the face
    coherence: float      # candidates' neighbours that are candidates, above chance (0: speckle, 1: one region)
    candidates: float     # share of the face pixels that are candidates

    def describe(self) -> str:
        return (f"cut {self.threshold:.4f} ({self.rule}); candidates {self.candidates:.1%} of the face, "
                f"{self.contrast:.4f} darker than the rest, coherence {self.coherence:.2f} (0: speckle)")


def measure(diffs, faces, threshold, relative: float = RELATIVE) -> Response:
    """The cut and the contrast/coherence of centred differences ``diffs`` (HxW each) on their ``faces`` masks."""
    values = np.concatenate([d[f] for d, f in zip(diffs, faces)]) if len(diffs) else np.zeros(0)
    p99 = float(np.quantile(values, 0.99)) if values.size else 0.0
    if threshold == "otsu":
        thr, rule = otsu_threshold(values), "otsu over every centred difference on the face"
        check_two_modes(values, thr)
    elif threshold == "relative":
        thr, rule = relative * p99, f"relative: {relative:g} x the 99th percentile ({p99:.4f})"
    else:
        thr = float(threshold)
        rule = f"fixed (the authors' recipe: {RECIPE_THRESHOLD})" if thr == RECIPE_THRESHOLD else "fixed (given)"
    inside = outside = kept = n_cand = n_face = 0.0
    n_in = n_out = 0
    for d, f in zip(diffs, faces):
        cand = (d > thr) & f if thr > 0 else np.zeros_like(f)
        inside += float(d[cand].sum()); n_in += int(cand.sum())
        rest = f & ~cand
        outside += float(d[rest].sum()); n_out += int(rest.sum())
        kept += float(_neighbours(cand)[cand].sum()) / 8; n_cand += float(cand.sum()); n_face += float(f.sum())
    contrast = inside / max(n_in, 1) - outside / max(n_out, 1) if n_in else 0.0
    share = n_cand / n_face if n_face else 0.0
    # Coherence: how much more often a candidate's neighbours are candidates than chance (the candidates' share of
    # the face) would make them: 0 for speckle at any density, ~0.2 for a thin line, ~0.7 for a blob.
    rate = kept / n_cand if n_cand else 0.0
    coherence = (rate - share) / (1 - share) if n_cand and share < 1 else 0.0
    return Response(thr, rule, p99, contrast, coherence, share)


def _neighbours(mask: np.ndarray) -> np.ndarray:
    """How many of each pixel's 8 neighbours are set (int HxW)."""
    m = np.pad(np.asarray(mask, bool), 1).astype(np.int16)
    h, w = mask.shape
    return sum(m[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)) - m[1:-1, 1:-1]


def judge(response: Response, min_contrast: float | None, min_coherence: float | None, step, scope: str = "") -> None:
    """Refuse a DiFaReli whose response to c has too little spatial contrast or is speckle, naming what was
    measured (``min_contrast=0`` writes the maps whatever they are). ``scope`` ends the refusal."""
    need = MIN_CONTRAST if min_contrast is None else float(min_contrast)
    if need <= 0:
        return
    fix = "train the DiFaReli longer, or set min_contrast=0 to write the maps anyway"
    if response.threshold <= 0:
        raise errors.UserError(f"this DiFaReli does not darken any part of the face as c grows (step {step}): the "
                               f"{response.rule} gives a cut of {response.threshold:.4f} <= 0{scope}; {fix}")
    if response.contrast < need:
        raise errors.UserError(f"this DiFaReli's response to c has too little spatial contrast (step {step}): "
                               f"{response.describe()}, below min_contrast={need:g}{scope}; {fix}")
    coh = MIN_COHERENCE if min_coherence is None else float(min_coherence)
    if response.coherence < coh:
        raise errors.UserError(f"this DiFaReli's response to c is speckle, not a shadow (step {step}): "
                               f"{response.describe()}; below min_coherence={coh:g}{scope}; {fix}")
