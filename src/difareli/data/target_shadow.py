"""The shadow strength c' a target gets when none is given (SPEC 5.2, 12): a photo's (:func:`photo_shadow`), a
benchmark pair's, the c a user has for a target image (:func:`target_shadow_of`), each with a sentence saying where
it came from, and the median shadowed c of a split (:func:`split_typical_c`) that a rotation video of an unshadowed
record falls back on (its rule: :func:`difareli.relight.request.video_shadow`).
"""

from __future__ import annotations

import math

import numpy as np

from difareli.data import encodings
from difareli.errors import UserError

#: A record counts as shadowed when its cast shadows remove at least this share of the light (c >= logit of it).
SHADOWED_SHARE = 0.01
SHADOWED_C = math.log(SHADOWED_SHARE / (1 - SHADOWED_SHARE))
_TYPICAL_C: dict[tuple[str, str], float | None] = {}
#: A photo's target shadow strength when none is given, normalised (the app's slider; ``encodings.normalise_c``:
#: c' = -1.83, 14% of the light removed), unless its own is stronger. Measured on the four frontal photos of
#: scripts/photo_presets_bench.py under left, right and top (docs/photo_quality.md): the photos' own c (about
#: 0.48) drew no visible nose shadow, 0.75 a faint one, 0.875 a visible one (cast-shadow response 1.3-2.3), 1.0 a
#: dark blotch (1.5-3.0, three times what the light predicts).
PHOTO_SHADOW = 0.875


def photo_shadow(own: float | None) -> tuple[float, str]:
    """The shadow strength c' a photo's target gets when none is given, and a sentence saying so: the photo's own
    c where it is stronger than :data:`PHOTO_SHADOW`, else that strength (a photo's own c is its estimate of the
    shadows it has, and a frontal photo has almost none: kept, a new light drew none)."""
    default = encodings.denormalise_c(PHOTO_SHADOW)
    if own is not None and own >= default:
        return own, f"target c' = {own:.3f} (the photo's own c)"
    return default, (f"target c' = {default:.3f} (a photo's default strength {PHOTO_SHADOW:g}; its own c "
                     f"{'unknown' if own is None else f'{own:.3f}'} is weaker; give target.shadow to change it)")


def typical_shadowed_c(shadows) -> float | None:
    """The median c of the records whose cast shadows remove at least ``SHADOWED_SHARE`` of the light."""
    c = np.asarray(shadows, dtype=np.float64).reshape(-1)
    shadowed = c[np.isfinite(c) & (c >= SHADOWED_C)]
    return float(np.median(shadowed)) if shadowed.size else None


def split_typical_c(store, split: str = "train") -> float | None:
    """:func:`typical_shadowed_c` of the stored ``shadow`` of ``split``'s records (cached per store)."""
    key = (str(store.root), split)
    if key not in _TYPICAL_C:
        ids = store.ids(split=split) if store.available("shadow") else []
        _TYPICAL_C[key] = typical_shadowed_c([store.read(r, ["shadow"])["shadow"][0] for r in ids]) if ids else None
    return _TYPICAL_C[key]


def stored_shadow_is_estimate(store) -> bool:
    """Whether a store's ``shadow`` is what a user has (an estimator's c): photo stores and SynthFaces
    ``inputs=estimated`` (v3) or ``estimated_light`` (v2); a SynthFaces ``inputs=exact`` store holds the exact c
    there (an oracle)."""
    meta = store.store_meta
    return meta.get("generator") != "synthfaces" or meta.get("inputs") in ("estimated", "estimated_light")


def target_shadow_of(store, record_id: str, *, oracle: bool = False, split: str = "train") -> tuple[float | None, str]:
    """``(c', how)``: the shadow strength a user has for a target given by ``record_id``'s image.

    ``oracle``: the exact c (``shadow_gt``, else ``shadow``). Otherwise the stored ``shadow`` when it is an
    estimate (:func:`stored_shadow_is_estimate`), else the stated policy: ``split``'s median shadowed c."""
    if not store.available("shadow"):
        return None, "no target c (the store has no 'shadow' encoding)"
    if oracle:
        name = "shadow_gt" if store.available("shadow_gt") else "shadow"
        return encodings.shadow_logit(store.read(record_id, [name]), name), "exact c (oracle)"
    if stored_shadow_is_estimate(store):
        return (encodings.shadow_logit(store.read(record_id, ["shadow"])),
                "c estimated from the target image (stored 'shadow': the shadow classifier)")
    c = split_typical_c(store, split)
    if c is None:
        raise UserError(f"store {store.root} holds only exact shadow c and its {split} split has no shadowed record to "
                        "take a typical c from; use an inputs=estimated store or set oracle_shadow=true")
    return c, f"c = {c:.3f}, the {split} split's median shadowed c (the store holds only exact c)"
