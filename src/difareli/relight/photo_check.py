"""A check before relighting: will this photo relight well? One line per photo.

Measured on the prepared photo (:class:`~difareli.relight.photo.PreparedPhoto`), nothing relit:

- ``face_px``: the side of the aligned square in photo pixels (the model enlarges anything smaller than its crop);
- ``yaw_deg`` / ``pitch_deg``: the fitted head pose (BFM fit), SynthFaces' training range is the frontal half;
- ``landmark_px``: the BFM fit's landmark residual in crop pixels (a bad fit: wrong shading and shadow maps);
- ``light_rel_rmse``: the light fit's relative residual on the skin (a light SH cannot explain: hard shadows,
  coloured light, make-up);
- ``past_edge``: the share of the crop past the photo's edge (padding the model has to relight);
- ``code_z``: how far the shape / identity codes lie from the training store's (the largest |z| over the code's
  dimensions against a store's mean and standard deviation), when a store is given.

Thresholds (:data:`LIMITS`) are provisional (docs/photos.md: not yet calibrated against the DSSIM of SynthFaces
renders made small, turned and badly lit). Verdict: ok or poor with what to do; ``strict=true`` refuses a poor photo.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

#: name -> (limit, the fix said when over it). A measure over its limit makes the verdict "poor".
LIMITS: dict[str, tuple[float, str]] = {
    "face_px": (32.0, "use a larger photo of the face (at least 32 px between the eyes' square sides)"),
    "yaw_deg": (35.0, "use a photo facing the camera (head turned at most 35 degrees)"),
    "pitch_deg": (30.0, "use a photo with the head level (tilted at most 30 degrees)"),
    "landmark_px": (2.5, "the face model fit poorly (glasses, occlusion, expression?): try a clearer photo"),
    "light_rel_rmse": (0.25, "the light is not one soft light (hard shadows, coloured light): expect weak relights"),
    "past_edge": (0.35, "the face is cropped tightly: use a photo with more room around the head"),
    "code_z": (6.0, "the face lies far from the training faces: expect weak relights"),
}


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
        """One line: ``<what>: ok (...)`` or ``<what>: poor: <why>; <fix>``."""
        shown = ", ".join(f"{k} {v:.3g}" for k, v in self.measures.items())
        if self.ok:
            return f"{self.what}: will relight well ({shown})"
        return f"{self.what}: may relight poorly: {'; '.join(self.problems)} ({shown})"


def code_stats(store, names=("shape", "identity"), limit: int = 256) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Mean and standard deviation of the codes ``names`` over up to ``limit`` records of a training store."""
    ids = (store.ids(split="train") or store.ids())[:limit]
    out = {}
    for name in names:
        if not store.available(name):
            continue
        a = np.stack([np.asarray(store.read(i, [name])[name], np.float64).ravel() for i in ids])
        out[name] = (a.mean(0), a.std(0) + 1e-6)
    return out


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
            cmp = "<" if name == "face_px" else ">"
            result.problems.append(f"{name} {value:.3g} {cmp} {limit:g}: {fix}")
    return result
