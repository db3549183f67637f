"""A check before relighting: will this photo relight well? One line per photo.

Measured on the prepared photo (:class:`~difareli.relight.photo.PreparedPhoto`), nothing relit:

- ``face_px``: the side of the aligned square in photo pixels (the model enlarges anything smaller than its crop);
- ``yaw_deg`` / ``pitch_deg``: the fitted head pose (BFM fit), SynthFaces' training range is the frontal half;
- ``landmark_px``: the BFM fit's landmark residual in crop pixels (a bad fit: wrong shading and shadow maps);
- ``light_rel_rmse``: the light fit's relative residual on the skin (a light SH cannot explain: hard shadows,
  coloured light, make-up);
- ``past_edge``: the share of the crop past the photo's edge (padding the model has to relight);
- ``face_outside``: the share of the face (its parts in the crop's masks) lying past the photo's edge: a face the
  photo cuts, which the model relights from reflected padding (the 112 px tight crop of issue 61 had 14%, past_edge
  0.37 under its limit, and gave the worst artefact);
- ``code_z``: how far the shape / identity codes lie from the training store's (the largest |z| over the code's
  dimensions against given means and standard deviations, ``stats``), where a caller gives them (no command does).

Limits (:data:`LIMITS`): ``face_px``, ``yaw_deg`` and ``past_edge`` are measured (``scripts/calibrate_photo_check.py``,
docs/photos.md): 1,632 SynthFaces photos of 48 unseen heads made small, turned, tilted, badly lit and cut, relit
by ``difareli_pp_ss-synth64``, each limit where the relights' DSSIM stays over 0.02 above the same head's clean
photo's (:func:`choose_limit`). ``pitch_deg``, ``light_rel_rmse``, ``landmark_px``, ``face_outside`` and ``code_z``
stay provisional: the renders found no stable limit for the first two, ``landmark_px`` on them only re-reads the
pose, ``face_outside``'s 5% is where the bench's uncut photos read 0 and its cut ones 14-45%
(``scripts/photo_presets_bench.py``'s photos), and ``code_z`` needs ``stats``. Verdict: ok or poor with what to do,
said in plain words (:data:`WORDS`; the measures keep their names in a folder's relight.csv); ``strict=true``
refuses a poor photo.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from difareli.data.encodings import FACE_PARTS, PART_INDEX

#: name -> (limit, the fix said when over it). A measure over its limit makes the verdict "poor"; face_px, yaw_deg
#: and past_edge as measured (module doc), the others provisional.
LIMITS: dict[str, tuple[float, str]] = {
    "face_px": (27.9, "use a larger photo of the face (the face at least 28 px wide)"),
    "yaw_deg": (27.6, "use a photo facing the camera (head turned at most about 28 degrees)"),
    "pitch_deg": (30.0, "use a photo with the head level (tilted at most 30 degrees)"),
    "landmark_px": (2.5, "the face model fit poorly (glasses, occlusion, expression?): try a clearer photo"),
    "light_rel_rmse": (0.25, "the light is not one soft light (hard shadows, coloured light): expect weak relights"),
    "past_edge": (0.442, "the face is cropped tightly: use a photo with more room around the head"),
    "face_outside": (0.05, "use a photo with the whole face in it and room around the head"),
    "code_z": (6.0, "the face lies far from the training faces: expect weak relights"),
}


#: Each measure's amount in plain words, and the sentence it goes in (the line a user reads).
UNITS = {"face_px": "{:.0f} px", "yaw_deg": "{:.0f} degrees", "pitch_deg": "{:.0f} degrees",
         "landmark_px": "{:.1f} px", "light_rel_rmse": "{:.0%}", "past_edge": "{:.0%}", "face_outside": "{:.0%}",
         "code_z": "{:.1f}"}
WORDS = {
    "face_px": "the face is {} wide",
    "yaw_deg": "the head is turned {}",
    "pitch_deg": "tilted {}",
    "landmark_px": "the face model's landmarks off by {}",
    "light_rel_rmse": "the light fit off by {} on the skin",
    "past_edge": "{} of the face's square lies outside the photo",
    "face_outside": "{} of the face lies outside the photo",
    "code_z": "the face lies {} standard deviations from the training faces",
}


def say(name: str, value: float) -> str:
    """One measure in plain words (its name where :data:`WORDS` has none)."""
    return WORDS[name].format(UNITS[name].format(value)) if name in WORDS else f"{name} {value:.3g}"


@dataclass
class Check:
    """The measures of one photo and its verdict."""

    what: str
    measures: dict[str, float] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def line(self) -> str:
        """One line in plain words: ``<what>: will relight well (...)`` or ``<what>: may relight poorly: <why>: <fix>
        (...)``."""
        # Each measure once (a problem already says its own), a share outside the photo only when there is one.
        words = [say(k, v) for k, v in self.measures.items() if v > 0 or k not in ("past_edge", "face_outside")]
        shown = ", ".join(w for w in words if not any(p.startswith(w) for p in self.problems))
        if self.ok:
            return f"{self.what}: will relight well ({shown})"
        return f"{self.what}: may relight poorly: {'; '.join(self.problems)} ({shown})"


def measure(prepared, stats: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None) -> dict[str, float]:
    """The measures of the module doc (those the prepared photo has)."""
    meta = prepared.meta
    quad = np.asarray(prepared.quad, np.float64)
    out = {"face_px": float(np.hypot(*(quad[3] - quad[0])) / 2.0)}  # ~ the face's width: the square is 2x it
    fit = meta.get("bfm_fit") or {}
    if fit.get("pose_deg") is not None:
        yaw, pitch = fit["pose_deg"][:2]
        out["yaw_deg"], out["pitch_deg"] = abs(float(yaw)), abs(float(pitch))
    if fit.get("rmse_px") is not None:
        out["landmark_px"] = float(fit["rmse_px"])
    light = meta.get("light_fit") or {}
    if light.get("rel_rmse") is not None:
        out["light_rel_rmse"] = float(light["rel_rmse"])
    out["past_edge"] = float(prepared.past_edge)
    masks, inside = prepared.arrays.get("masks"), prepared.inside
    if masks is not None and inside is not None:
        face = np.isin(np.asarray(masks), [PART_INDEX[p] for p in FACE_PARTS])
        out["face_outside"] = float((face & ~np.asarray(inside, bool)).sum() / max(int(face.sum()), 1))
    if stats:
        z = [np.abs((np.asarray(prepared.arrays[n], np.float64).ravel() - m) / s).max()
             for n, (m, s) in stats.items() if n in prepared.arrays]
        if z:
            out["code_z"] = float(max(z))
    return out


def check(prepared, what: str, stats=None, limits: Mapping[str, tuple[float, str]] = LIMITS) -> Check:
    """The :class:`Check` of one prepared photo."""
    result = Check(what, measure(prepared, stats))
    for name, value in result.measures.items():
        if name not in limits:
            continue
        limit, fix = limits[name]
        bad = value < limit if name == "face_px" else value > limit
        if bad:
            bound = UNITS[name].format(limit) if name in UNITS else f"{limit:g}"
            result.problems.append(f"{say(name, value)}, {'under' if name == 'face_px' else 'over'} {bound}: {fix}")
    return result


def choose_limit(values, dssim, reference: float, *, margin: float, worse: str = "higher",
                 bin_size: int = 8) -> float | None:
    """The limit a calibration reads off photos' measures ``values`` and their relights' ``dssim``: the photos
    sorted from good to bad (``worse``: "higher" or "lower" values are bad) in bins of ``bin_size`` (the
    remainder joins the last bin); the limit lies midway between the final run of bins whose median DSSIM exceeds
    ``reference + margin`` and the photo before it. None where the worst bin does not exceed it, or every bin
    does (no limit within the data)."""
    v, d = np.asarray(values, np.float64), np.asarray(dssim, np.float64)
    order = np.argsort(-v if worse == "lower" else v, kind="stable")
    v, d = v[order], d[order]
    edges = [i * bin_size for i in range(max(1, len(v) // bin_size))] + [len(v)]
    # A run that reaches the worst bin, not any single noisy bin: the limit is where relights stay worse.
    over = [bool(np.median(d[a:b]) > reference + margin) for a, b in zip(edges[:-1], edges[1:])]
    if not over or not over[-1] or all(over):
        return None
    first = len(over) - 1
    while over[first - 1]:
        first -= 1
    i = edges[first]
    return float((v[i - 1] + v[i]) / 2)
