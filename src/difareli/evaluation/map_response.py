"""How much a DiFaReli++ follows the shadow map it is given: a record relit with a map and with the map zeroed.

For a record of a SynthFaces store: invert it with its own condition, then decode (one batch, the same inversion)
under its own light twice, once with the shadow-map channel holding a map ``M`` and once with it zeroed. The
**darkening** is the mean luminance drop inside ``M`` less the drop on the rest of the face (a change of the
whole face's brightness is not a shadow); the drop inside ``M`` alone is reported beside it. Both are compared
with what a real cast shadow removes on the same record: ``Y * f / (1 - f)`` averaged over its visibly shadowed
pixels (``shadow_visible_gt``), ``f`` the share of the pixel's light the shadows take (``shadow_fraction_gt``;
images are linear, so the unshadowed pixel is ``Y / (1 - f)``). A model that draws the shadow it is given scores
a ratio near 1; one that ignores its map, 0.

The maps tried (``MAPS``): ``exact`` (the visible shadows times the exact c), ``march_exact`` (the relight's own
maker toward the exact light, i.e. the suns the record's header names, with the exact c) and ``march_fitted``
(toward the stored, fitted light with the stored c: what a relight of a photo has).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from difareli.data import encodings
from difareli.data.inputs import read_record
from difareli.lighting.suns import Suns
from difareli.relight.targets import Targets
from difareli.render.retarget import target_shadow_map
from difareli.utils import imageops

MAPS = ("exact", "march_exact", "march_fitted")
#: A record counts as shadowed when its visible shadows cover at least this share of its face.
SHADOWED_SHARE = 0.04
READS = ("face_mask", "shadow_visible_gt", "shadow_fraction_gt", "light_gt", "shadow_gt", "depth", "normal", "cam")


def shadowed_records(store, ids, share: float = SHADOWED_SHARE) -> list[str]:
    """The records of ``ids`` whose visible shadows cover at least ``share`` of the face."""
    out = []
    for rid in ids:
        a = store.read(rid, ["face_mask", "shadow_visible_gt"])
        face = np.asarray(a["face_mask"], bool)
        if face.any() and (np.asarray(a["shadow_visible_gt"], bool) & face).sum() >= share * face.sum():
            out.append(rid)
    return out


def make_map(arrays, kind: str, header=None) -> np.ndarray:
    """The map ``kind`` of one record (float32 HxW, binary times the normalised c); ``header`` (``store.meta``):
    the suns ``march_exact`` marches toward (else the SH ``light_gt``)."""
    rng = encodings.store_c_range(arrays)
    if kind == "exact":
        c = encodings.shadow_logit(arrays, "shadow_gt")
        return (np.asarray(arrays["shadow_visible_gt"], bool) * encodings.normalise_c(c, rng)).astype(np.float32)
    light, c = ("light_gt", "shadow_gt") if kind == "march_exact" else ("light", "shadow")
    sh_light = np.asarray(arrays[light], np.float64)
    suns = Suns.from_header(header, sh_light) if kind == "march_exact" and header else None
    return target_shadow_map(arrays, sh_light if suns is None else suns, encodings.shadow_logit(arrays, c), rng)


def real_removal(arrays) -> float:
    """Mean luminance a real cast shadow removes on the record's visibly shadowed face pixels."""
    y = imageops.luminance(np.asarray(arrays["image"], np.float64) / 255.0)
    f = np.clip(np.asarray(arrays["shadow_fraction_gt"], np.float64), 0.0, 0.95)
    where = np.asarray(arrays["shadow_visible_gt"], bool) & np.asarray(arrays["face_mask"], bool)
    return float((y * f / (1 - f))[where].mean()) if where.any() else float("nan")


@dataclass
class RecordResponse:
    record: str
    kind: str
    darkening: float       # inside the map less the rest of the face (luminance in [0, 1])
    inside: float          # the drop inside the map alone
    real: float            # what a real cast shadow removes on this record
    map_share: float       # share of the face the map covers


def respond(relighter, store, rid: str, kinds=MAPS) -> list[RecordResponse]:
    """The darkening of each map ``kinds`` on record ``rid``: the record under its own light (re-rendered, as every
    relight's targets are) with each map and with it zeroed, through :meth:`Relighter.relight_many` (one inversion,
    every decode in one batch; float luminance)."""
    arrays = read_record(store, rid, list(dict.fromkeys([*relighter.needed_encodings(), "image", *READS])))
    source = relighter.source_from_arrays(arrays, f"record {rid!r} of {store.root}")
    maps = [make_map(arrays, k, store.meta(rid)) for k in kinds]
    given = np.stack([m * on for m in maps for on in (1.0, 0.0)])
    targets = Targets.of([arrays["light"]] * len(given), None, f"own light of record {rid!r}", maps=given)
    y = imageops.luminance(relighter.relight_many([source], [targets], as_float=True)[0].astype(np.float64))
    face = np.asarray(arrays["face_mask"], bool)
    real = real_removal(arrays)
    out = []
    for i, (kind, m) in enumerate(zip(kinds, maps)):
        inside, drop = (m > 0) & face, y[2 * i + 1] - y[2 * i]
        rest = face & ~inside
        dark = float(drop[inside].mean() - drop[rest].mean()) if inside.any() and rest.any() else float("nan")
        alone = float(drop[inside].mean()) if inside.any() else float("nan")
        out.append(RecordResponse(rid, kind, dark, alone, real, float(inside.sum() / max(face.sum(), 1))))
    return out


def summarise(rows: list[RecordResponse]) -> dict[str, dict[str, float]]:
    """Per map kind: the ratio of mean darkening to mean real removal, both means with SEs, and the records."""
    out = {}
    for kind in dict.fromkeys(r.kind for r in rows):
        d = np.array([r.darkening for r in rows if r.kind == kind and np.isfinite(r.darkening)])
        alone = np.array([r.inside for r in rows if r.kind == kind and np.isfinite(r.inside)])
        real = np.array([r.real for r in rows if r.kind == kind and np.isfinite(r.real)])
        se = lambda v: float(v.std(ddof=1) / np.sqrt(len(v))) if len(v) > 1 else float("nan")  # noqa: E731
        out[kind] = {"ratio": float(d.mean() / real.mean()) if len(d) and len(real) else float("nan"),
                     "darkening": float(d.mean()) if len(d) else float("nan"), "darkening_se": se(d),
                     "inside": float(alone.mean()) if len(alone) else float("nan"),
                     "inside_ratio": float(alone.mean() / real.mean()) if len(alone) and len(real) else float("nan"),
                     "real": float(real.mean()) if len(real) else float("nan"), "records": int(len(d))}
    return out
