"""Moving-light videos, measured: a record relit under a rotating light beside its ground truth.

What is measured per frame (relit vs ground truth, on the record's face mask):

- DSSIM / MSE / LPIPS (``metrics.evaluate``);
- **shadow IoU**: the cast shadow :func:`detect_cast_shadow` finds in the relit frame against the GT frame's exact
  visible shadows (SynthFaces' ``shadow_visible_gt`` of that frame) on the pixels the rule judges, and the same
  rule's IoU on the GT frame (``rule_iou``: how well the detector finds the real shadows; a relit frame whose
  shadow is darker than the real one can score above it) and on the GT frame rendered without cast shadows
  (``floor_iou``: what a relight that draws none scores, about 0.02 on five unseen records:
  ``scripts/video_rule_quality.py``); comparing the relit frame's detection with the GT frame's
  instead would have given those frames 0.31, the two detections sharing the rule's errors on all but cast shadows;
- **temporal consistency**: the frame-to-frame change ``mean |f[t+1] - f[t]|`` (face mask, [0, 1] units) of the
  relit sequence and of the GT, and the temporal error ``mean |(r[t+1] - r[t]) - (g[t+1] - g[t])|``.

Shadow detection rule (the same for relit and GT frames; it reads the lights, never the GT's shadows): an albedo
proxy is the input image divided by the input light's unshadowed irradiance on the stored normals; a frame predicts,
without cast shadows, ``albedo * E_open(n)`` under its light; a pixel is in cast shadow when its luminance is below
``1 - VISIBLE`` of that prediction, i.e. when shadows take more than ``VISIBLE`` of its light: SynthFaces' own
definition of a visible shadow (``SynthConfig.shadow_visible``, 0.25). Pixels are judged only on the face mask where
the normal is known, the input is lit enough for the albedo proxy (``Y(E_input) > MIN_INPUT_IRRADIANCE``) and not in
its own stored cast shadow, and where the frame's key sun carries more than ``VISIBLE`` of the pixel's light (only
there can its cast shadow be seen). The lights are :class:`~difareli.lighting.suns.Suns`, the suns and ambient a
SynthFaces record is rendered with: a 9-term SH cannot hold a sun's sharp ``max(0, n.d)`` falloff, and the rule
that predicted with it (before 2026-12-05) found the ground truth's own visible shadows at IoU 0.325 on the five
records of docs/shadow_maps.md's video tables, the exact suns at 0.545 (``scripts/video_rule_quality.py``; the
share 0.25 chosen on ten train-split records of ``data/sf_v3_64``: 0.520, 0.48-0.52 over 0.15-0.4).
difareli-video applies it with the exact lights (the input's and each GT frame's) where the store has them: the rule
is a measurement, not a model input.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch

from difareli.errors import UserError
from difareli.lighting import sh
from difareli.lighting.suns import Suns
from difareli.data.encodings import known_normals
from difareli.utils.fileio import atomic_path
from difareli.utils.imageops import LUMA
from difareli.evaluation.adherence import shadow_scores

#: The share of a pixel's light its cast shadows must take to count as visible (SynthFaces' ``shadow_visible``).
VISIBLE = 0.25
MIN_INPUT_IRRADIANCE = 0.15


def _unit(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, dtype=np.float64) / 255.0 if np.asarray(x).dtype == np.uint8 else np.asarray(x, np.float64)


def _irradiance(light: Suns | np.ndarray, normal: np.ndarray) -> np.ndarray:
    # Suns: the exact unshadowed irradiance; a bare 9x3 SH light (no suns known): its smooth SH irradiance.
    return light.irradiance(normal) if isinstance(light, Suns) else sh.irradiance(np.asarray(light, np.float64), normal)


def judged_region(arrays: Mapping[str, np.ndarray], input_light: Suns | np.ndarray | None = None) -> np.ndarray:
    """Pixels where the shadow rule can judge (before the per-frame key-sun test), (H, W) bool; ``input_light``
    defaults to ``arrays["light"]``."""
    normal = np.asarray(arrays["normal"], dtype=np.float64)
    e_in = _irradiance(arrays["light"] if input_light is None else input_light, normal) @ LUMA
    own = np.asarray(arrays["shadow_map"]) > 0 if "shadow_map" in arrays else False
    return (np.asarray(arrays["face_mask"], bool) & known_normals(normal)
            & (e_in > MIN_INPUT_IRRADIANCE) & ~own)


def detect_cast_shadow(frames: np.ndarray, arrays: Mapping[str, np.ndarray], lights: Sequence[Suns | None],
                       input_light: Suns | np.ndarray | None = None, visible: float = VISIBLE
                       ) -> tuple[np.ndarray, np.ndarray]:
    """``(shadow, judged)``, both (N, H, W) bool, for frames (N, H, W, 3) lit by ``lights`` (one
    :class:`Suns` per frame; None for a frame without a sun: nothing judged), by the module's rule; ``arrays``
    holds the input record's ``image``, ``normal``, ``face_mask`` (and ``shadow_map``, ``light``), ``input_light``
    (default ``arrays["light"]``) the input's light."""
    normal = np.asarray(arrays["normal"], dtype=np.float64)
    input_light = arrays["light"] if input_light is None else input_light
    albedo = _unit(arrays["image"]) / np.maximum(_irradiance(input_light, normal), 1e-3)
    region = judged_region(arrays, input_light)
    shadow, judged = [], []
    for frame, light in zip(np.asarray(frames), lights):
        if light is None:
            here = np.zeros_like(region)
            pred = np.ones(region.shape)
        else:
            e_open = light.irradiance(normal)
            pred = (albedo * e_open) @ LUMA
            key = light.terms(normal)[0] @ LUMA
            here = region & (key > visible * np.maximum(e_open @ LUMA, 1e-6))
        lum = _unit(frame) @ LUMA
        shadow.append(here & (lum < (1.0 - visible) * np.maximum(pred, 1e-6)))
        judged.append(here)
    return np.stack(shadow), np.stack(judged)


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-item IoU of boolean masks (N, ...) -> (N,); NaN where both are empty (``metrics.binary_scores``)."""
    from difareli.evaluation.metrics import binary_scores  # the image metrics load torchmetrics and LPIPS: 0.9 s

    return binary_scores(a, b)["iou"]


def frame_changes(frames: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``mean |f[t+1] - f[t]|`` over the mask pixels and channels, [0, 1] units, (N - 1,)."""
    f = _unit(frames)
    d = np.abs(np.diff(f, axis=0))[:, mask]
    return d.mean(axis=(1, 2)) if d.size else np.full(len(f) - 1, np.nan)


def temporal_error(relit: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``mean |(r[t+1] - r[t]) - (g[t+1] - g[t])|`` over the mask, (N - 1,): change the GT does not have."""
    d = (np.diff(_unit(relit), axis=0) - np.diff(_unit(gt), axis=0))[:, mask]
    return np.abs(d).mean(axis=(1, 2))


@dataclass
class VideoReport:
    """Per-frame measurements of a relit sequence against its ground truth."""

    # (N,) each: dssim, mse, lpips, shadow_iou, rule_iou [, floor_iou, map_adherence, map_iou]
    per_frame: dict[str, np.ndarray]
    changes: dict[str, np.ndarray] = field(default_factory=dict)  # relit, gt, error (N - 1,)

    def summary(self) -> dict[str, float]:
        out = {f"{k}_mean": float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")
               for k, v in self.per_frame.items()}
        out["shadow_frames"] = int(np.isfinite(self.per_frame["shadow_iou"]).sum())
        for k, v in self.changes.items():
            out[f"change_{k}_mean"] = float(np.mean(v))
        return out


def measure(relit: np.ndarray, gt: np.ndarray, arrays: Mapping[str, np.ndarray], lights: Sequence[Suns | None],
            gt_cast: np.ndarray, maps: np.ndarray | None = None,
            input_light: Suns | np.ndarray | None = None, shadowless: np.ndarray | None = None) -> VideoReport:
    """Measure relit frames (N, H, W, 3) against GT frames; ``lights`` (one :class:`Suns` per frame) and
    ``input_light`` (default ``arrays["light"]``) are the lights the detection rule uses, ``gt_cast`` (N, H, W)
    the GT frames' exact visible shadows, ``maps`` (N, H, W) the target shadow maps the relight was given: how far
    each frame follows its map (:func:`difareli.evaluation.adherence.shadow_scores`: ``map_adherence``, its
    darkening against the ground truth's under the same map, and ``map_iou``, the shadow found in the frame against
    the map); ``shadowless`` (N, H, W, 3) the GT frames rendered without cast shadows: their shadow IoU
    (``floor_iou``) is what a relight that draws no cast shadow scores."""
    from difareli.evaluation import metrics  # (as in iou)

    if relit.shape != gt.shape:
        raise UserError(f"relit frames {relit.shape} and ground truth {gt.shape} differ in shape")
    mask = np.asarray(arrays["face_mask"], bool)
    to_t = lambda f: torch.from_numpy(_unit(f)).permute(0, 3, 1, 2)  # noqa: E731
    m = torch.from_numpy(np.broadcast_to(mask, relit.shape[:3]).copy())
    scores = {k: v.numpy() for k, v in metrics.evaluate(to_t(relit), to_t(gt), m).items()}
    found, judged = detect_cast_shadow(relit, arrays, lights, input_light)
    truth = np.asarray(gt_cast, bool) & judged
    scores["shadow_iou"] = iou(found, truth)
    scores["rule_iou"] = iou(detect_cast_shadow(gt, arrays, lights, input_light)[0], truth)
    if shadowless is not None:
        scores["floor_iou"] = iou(detect_cast_shadow(shadowless, arrays, lights, input_light)[0], truth)
    if maps is not None:
        follow = [shadow_scores(r, g, mask, np.asarray(m) > 0) for r, g, m in zip(relit, gt, maps)]
        scores["map_adherence"] = np.array([f["shadow_adherence"] for f in follow])
        scores["map_iou"] = np.array([f["shadow_iou"] for f in follow])
    changes = {"relit": frame_changes(relit, mask), "gt": frame_changes(gt, mask),
               "error": temporal_error(relit, gt, mask)} if len(relit) > 1 else {}
    return VideoReport(scores, changes)


def write_csv(report: VideoReport, path: str | Path, angles: np.ndarray | None = None) -> Path:
    """One row per frame: angle, the per-frame scores and the change to the next frame."""
    path = Path(path)
    n = len(next(iter(report.per_frame.values())))
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:  # a killed run never leaves half a CSV
        w = csv.writer(f)
        cols = list(report.per_frame)
        w.writerow(["frame", "angle", *cols, *(f"change_{k}" for k in report.changes)])
        for i in range(n):
            ch = [f"{v[i]:.6g}" if i < len(v) else "" for v in report.changes.values()]
            w.writerow([i, "" if angles is None else f"{angles[i]:.3f}",
                        *(f"{report.per_frame[c][i]:.6g}" for c in cols), *ch])
    return path


def plot_temporal(report: VideoReport, path: str | Path, title: str = "") -> Path:
    """Frame-to-frame change of the relit sequence and of the GT, and the shadow IoU, per frame (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.2))
    for k, style in (("relit", "-"), ("gt", "--"), ("error", ":")):
        if k in report.changes:
            a.plot(report.changes[k], style, label=k)
    a.set_xlabel("frame t"), a.set_ylabel("mean |f[t+1] - f[t]|"), a.legend(), a.set_title("temporal change")
    b.plot(report.per_frame["shadow_iou"], label="relit vs GT's exact shadows")
    b.plot(report.per_frame["rule_iou"], "--", label="the rule on the GT")
    if "floor_iou" in report.per_frame:
        b.plot(report.per_frame["floor_iou"], ":", label="GT without cast shadows")
    b.set_ylim(0, 1), b.set_xlabel("frame"), b.set_ylabel("IoU"), b.legend(), b.set_title("cast-shadow IoU")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
