"""The per-image metrics beyond DSSIM / MSE / LPIPS and the strata of a benchmark pair, read from a store.

:class:`PairExtras` decides once per run which of :data:`tables.EXTRA_METRICS` the store allows (identity: the
descriptor's weights are installed, :mod:`.identity`; lighting error: the store has normals; shadow adherence: it
has a target shadow map, :data:`adherence.SHADOW_KEYS`) and says why a column is absent in :attr:`notes`; then
scores each relit image. The strata: the target record's light ``category`` (SynthFaces record meta) and the target
shadow's share of the scored face region.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from difareli.evaluation import adherence
from difareli.evaluation import identity as ident
from difareli.lighting.light_fit import LightFit

IDENTITY = ("identity_input", "identity_gt")
#: ``light_angle_gt``: the light fitted to the relit image against the one fitted to the ground truth, both on the
#: input's geometry (the truth scores 0; ``light_angle`` is against the target light as a user has it, fitted to
#: the light-source image, on which the ground truth itself scores far from 0: docs/evaluation.md).
LIGHT = ("light_angle", "light_rel_error", "light_angle_gt")
SHADOW = ("shadow_adherence", "shadow_darkening", "shadow_iou")


class PairExtras:
    """Extra metrics and strata of benchmark pairs on ``store`` scored on ``score_mask`` (see the module doc)."""

    def __init__(self, store, score_mask: str = "face_mask", *, identity: bool = True, fit: LightFit | None = None,
                 min_share: float = adherence.MIN_SHARE, detect_rel: float = adherence.DETECT_REL):
        self.store, self.score_mask, self.fit = store, score_mask, fit or LightFit()
        self.min_share, self.detect_rel = float(min_share), float(detect_rel)
        self.notes: list[str] = []
        why = ident.unavailable() if identity else "identity columns left out: identity=false"
        self.identity = why is None
        if why:
            self.notes.append(why)
        self.light = store.available("normal") and store.available("face_mask")
        if not self.light:
            self.notes.append(f"lighting-error columns left out: store {store.root} has no normal map to fit on")
        self.shadow_key = next((k for k in adherence.SHADOW_KEYS if store.available(k)), None)
        if self.shadow_key is None:
            self.notes.append(f"shadow columns left out: store {store.root} has none of "
                              f"{', '.join(adherence.SHADOW_KEYS)}")
        self.category = any("category" in store.meta(r) for r in store.ids()[:1])

    def metrics(self) -> list[str]:
        """The extra metric columns this run scores."""
        return [*(IDENTITY if self.identity else ()), *(LIGHT if self.light else ()),
                *(SHADOW if self.shadow_key else ())]

    def strata(self) -> list[str]:
        """The strata columns this run records."""
        return [*(["light_category"] if self.category else []), *(["shadow_share"] if self.shadow_key else [])]

    def provenance(self) -> dict[str, str]:
        """What the extra metrics read, for provenance.json and the summary's Inputs line."""
        out = {}
        if self.shadow_key:
            out["target shadow M"] = (f"{self.shadow_key} > 0 of the target (scored where it covers "
                                      f"{self.min_share:g}-{1 - self.min_share:g} of the face; detector: "
                                      f"luminance below (1 - {self.detect_rel:g}) x the face median)")
        if self.identity:
            out["identity"] = "cosine of dlib's 128-d descriptor, each face upsampled to a 150 px aligned chip"
        return out

    def info(self, target, face: np.ndarray | None = None) -> dict[str, str]:
        """The strata of a pair whose ground truth is ``target`` (a :class:`~.pairs.StoredFace`; ``face``: its
        scored region, read if None)."""
        out = {}
        if self.category:
            out["light_category"] = str(self.store.meta(target.id).get("category", ""))
        if self.shadow_key:
            a = target.read([self.score_mask, self.shadow_key])
            face = a[self.score_mask] if face is None else face
            out["shadow_share"] = repr(adherence.shadow_share(face, np.asarray(a[self.shadow_key]) > 0))
        return out

    def empty(self, target) -> tuple[dict[str, float], dict[str, str]]:
        """NaN scores (a failed relight) with the pair's strata."""
        return {k: math.nan for k in self.metrics()}, self.info(target)

    def __call__(self, relit: np.ndarray, source, target, light: Any) -> tuple[dict, dict]:
        """(extra scores, strata) of ``relit`` (uint8 HxWx3): ``source`` relit toward ``light``, ground truth
        ``target`` (each a :class:`~.pairs.StoredFace`: what the benchmark read of them is not read again)."""
        out: dict[str, float] = {}
        gt = target.read(["image", self.score_mask])
        face = np.asarray(gt[self.score_mask], bool)
        if self.identity:
            src = source.read(["image", "face_mask"])
            tgt_face = target.read(["face_mask"])["face_mask"]
            sims = ident.similarities(relit, src["face_mask"], {"input": (src["image"], src["face_mask"]),
                                                                "gt": (gt["image"], tgt_face)})
            out.update(identity_input=sims["input"], identity_gt=sims["gt"])
        if self.light:
            geometry = source.read([n for n in LightFit.ENCODINGS if n != "image" and self.store.available(n)])
            try:
                fitted = adherence.relit_light(relit, geometry, self.fit)
                angle, rel = adherence.light_error(fitted, light)
                vs_gt = adherence.light_error(fitted, adherence.relit_light(gt["image"], geometry, self.fit))[0]
            except ValueError:  # too few usable face pixels in the relit image (clipped or black): undefined
                angle, rel, vs_gt = math.nan, math.nan, math.nan
            out.update(light_angle=angle, light_rel_error=rel, light_angle_gt=vs_gt)
        if self.shadow_key:
            m = np.asarray(target.read([self.shadow_key])[self.shadow_key]) > 0
            out.update(adherence.shadow_scores(relit, gt["image"], face, m, min_share=self.min_share,
                                               rel=self.detect_rel))
        return out, self.info(target, face)
