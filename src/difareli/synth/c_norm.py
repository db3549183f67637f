"""The c range of a SynthFaces v3 store: its training split's, as the authors normalise c.

DiFaReli++'s shadow map is ``binary map * c_norm``; the authors take ``c_norm = (c - c_min) / (c_max - c_min)`` over
the training set. A v3 store records that range in its header (``encodings.C_RANGE_KEY``) once every record is
written, and every map that is scaled by c in it uses the same one: the stored ``shadow_map`` (ray-traced on the
estimated surface) and ``shadow_map_gt``, the difference maps (``jobs/shadow_maps``) and the target maps of
relighting and videos (``render.retarget.target_shadow_map``, given the range with the record).

Until then the two maps hold their binary masks. :func:`finalise` writes the range first (``state: scaling``), then
rewrites each record's two maps (binary = ``shadow_map > 0`` and ``shadow_visible_gt``: idempotent, so a killed
run is finished by rerunning the same ``difareli-synth`` command), then marks it ``final``.
``c_quantile`` > 0 takes the range between the split's quantiles (the estimated c has outliers: one record of
3,200 at -39.6 in v2, docs/shadow_maps.md); 0 is the authors' strict min and max.
"""

from __future__ import annotations

import numpy as np

from difareli.data import derived
from difareli.data.encodings import C_RANGE_KEY, normalise_c, shadow_logit, store_c_range


def train_c_range(store, quantile: float, split: str = "train") -> dict:
    """``{"lo", "hi", "split", "quantile", "records"}`` of the stored ``shadow`` over ``split`` (all records if
    empty)."""
    ids = store.ids(split=split) or store.ids()
    c = np.array([shadow_logit(store.read(r, ["shadow"])) for r in ids], dtype=np.float64)
    c = c[np.isfinite(c)]
    lo, hi = (float(v) for v in np.quantile(c, [quantile, 1.0 - quantile]))
    if not hi > lo:  # every c equal: any range gives the same maps; keep them non-zero
        lo -= 1.0
    return {"lo": round(lo, 6), "hi": round(hi, 6), "split": split if store.ids(split=split) else "all",
            "quantile": float(quantile), "records": int(len(c)), "of": "shadow"}


def finalise(store, quantile: float) -> dict:
    """Record the train split's c range and scale every record's ``shadow_map``/``shadow_map_gt`` by it."""
    have = store.store_meta.get(C_RANGE_KEY)
    if isinstance(have, dict) and have.get("state") == "final":
        return have
    rng = {**train_c_range(store, quantile), "state": "scaling"}
    derived.update_header(store, C_RANGE_KEY, rng)
    c_range = store_c_range(store.store_meta)
    for rid in store.ids():
        a = store.read(rid, ["shadow", "shadow_gt", "shadow_map", "shadow_visible_gt"])
        derived.replace_base(store, rid, "shadow_map", scale_map(np.asarray(a["shadow_map"]) > 0,
                                                                 shadow_logit(a), c_range))
        derived.replace_base(store, rid, "shadow_map_gt", scale_map(a["shadow_visible_gt"],
                                                                    shadow_logit(a, "shadow_gt"), c_range))
    rng["state"] = "final"
    derived.update_header(store, C_RANGE_KEY, rng)
    return rng


def scale_map(binary: np.ndarray, c: float, c_range) -> np.ndarray:
    """``binary * normalise_c(c, c_range)`` as float32 (the ``shadow_map`` definition)."""
    return (np.asarray(binary, bool) * normalise_c(c, c_range)).astype(np.float32)
