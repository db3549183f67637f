"""DiFaReli++'s difference-method shadow maps from a trained DiFaReli (paper Sec. IV-A).

For every record: relight it with its own light at the largest and at the smallest shadow strength of the
training split (``c_max``, ``c_min``), through the relight door ``Relighter.relight_many`` (any sampler; records
inverted in batches, both targets decoded in one batch). The **difference** is ``Y(relit at c_min) - Y(relit at
c_max)`` (Rec. 709 luminance, images in [0, 1], not rounded): positive where the stronger shadow darkened the face.
Then, by the authors' recipe (XezXey/guided-diffusion ``experiment_scripts/TPAMI/cast_shadows/gen_smooth_sdiff/``):

Then (:mod:`difareli.jobs.shadow_response`): each record's difference is **centred** (its face median subtracted:
raising c also brightens the lit skin, a global change that is not a shadow), cut at a threshold **relative** to
the response (``relative`` x its 99th percentile; a number is the authors' fixed cut, 0.05 theirs; ``otsu``),
median-filtered, restricted to the mesh and the face less the eyes, brows and mouth, and scaled by the record's
normalised c. ``centre=none threshold=0.05`` is the authors' recipe (XezXey/guided-diffusion
``experiment_scripts/TPAMI/cast_shadows/gen_smooth_sdiff/``).

A DiFaReli is judged by the spatial contrast of its response (how much darker its candidate shadow pixels get
than the rest of the face) and its coherence (candidates that survive a 3x3 median), measured once ``check_after``
records are relit and again over all of them; a weak or speckled response is refused naming both numbers
(``min_contrast=0`` writes the maps anyway).

Inputs are checked before any relight: a threshold outside (0, 1), a split the store does not have, and a store
without a train split (the c range must come from the split the DiFaReli was trained on: ``split=``, or
``c_range=[c_min, c_max]``; a SynthFaces v3 store's recorded range is used, and said so, where it has one) are
refused. The store is locked for the run (:func:`difareli.utils.fileio.folder_lock`): a second writer is refused.

The raw differences are kept as the derived version ``shadow_map@diffraw-<hash>`` (resumable: a killed run
redoes only records without it), the maps as ``shadow_map@<version>`` (:mod:`difareli.data.derived`), both with their
provenance (the weights' content identity, sampler, c range, centring, threshold rule and value, median size) in
the store header: retrained weights at the same path are another version (``version=null`` names it by that
hash; a name given, the default ``difference``, already made with other settings is refused before any relight,
naming what differs).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
from tqdm.auto import tqdm

from difareli import errors
from difareli.checkpoints.loading import LoadedCheckpoint
from difareli.data import derived
from difareli.data import encodings
from difareli.utils import imageops
from difareli.utils.fileio import folder_lock
from difareli.relight.relightable import model_inputs
from difareli.relight.relighter import Relighter
from difareli.relight.targets import Targets
from difareli.jobs.shadow_response import (RECIPE_THRESHOLD, RELATIVE, Response, centred, check_centre,  # noqa: F401
                                           check_threshold, check_two_modes, finish_map, judge, measure,
                                           median_size, otsu_threshold)

#: Records relit before the DiFaReli's response to c is first judged (about 64 x 2,000 face pixels).
CHECK_AFTER = 64
ZERO_PARTS = ("l_eye", "r_eye", "l_brow", "r_brow", "mouth")
#: ``split=all``: the c range over every record of the store (said so in the provenance and the summary).
ALL = "all"


def store_splits(store) -> list[str]:
    """The split names the store's records carry (empty: its records name no split)."""
    return sorted({str(m["split"]) for m in store.index.values() if "split" in m})


def split_ids(store, split: str, key: str = "split") -> list[str]:
    """The records of ``split`` (``all``: every record); a split the store has no record of is refused, naming
    the splits it has (a misspelt ``split=trian`` never falls back to every record)."""
    if split == ALL:
        return store.ids()
    ids = store.ids(split=str(split))
    if not ids:
        have = store_splits(store)
        named = f"its splits: {', '.join(have)}" if have else "its records name no split"
        raise errors.UserError(f"{key}={split}: store {store.root} has no record with split={split} ({named}); give "
                               f"one of them, e.g. {key}={(have or [ALL])[0]}, or {key}={ALL} for every record")
    return ids


def c_source(store, split: str, given=None) -> tuple[list[str] | None, tuple[float, float] | None, str]:
    """Where the c range comes from, checked before any work: ``(ids, None, what)`` for the stored c of those
    records, ``(None, (lo, hi), what)`` for a given range or a v3 store's recorded one."""
    if given is not None:
        lo, hi = (errors.check_number(v, "c_range", allow_none=False) for v in given)
        if not hi > lo:
            raise errors.UserError(f"c_range={list(given)} is invalid: give [c_min, c_max] with c_min < c_max")
        return None, (lo, hi), f"c_range=[{lo:g}, {hi:g}] given"
    if split == "train" and not store.ids(split="train"):
        rng = store.store_meta.get(encodings.C_RANGE_KEY)
        stored = encodings.store_c_range(store.store_meta)
        if stored is not None and isinstance(rng, dict) and rng.get("state", "final") == "final":
            over = "every record's" if rng.get("split") == ALL else f"the {rng.get('split')} split's"
            return None, stored, (f"the store header's {encodings.C_RANGE_KEY}: {over} c at quantile "
                                  f"{rng.get('quantile')}, {rng.get('records')} records; this store has no train split")
        have = store_splits(store)
        named = f"its splits: {', '.join(have)}" if have else "its records name no split"
        raise errors.UserError(
            f"split=train: store {store.root} has no record with split=train ({named}), so the c range to relight at "
            "cannot be the training split's;\ngive the range the DiFaReli was trained with, c_range=[c_min,c_max] "
            "(printed by difareli-shadow-maps on its training store), or take it from split=<one of them> or "
            f"split={ALL}")
    ids = split_ids(store, split)
    what = "every record's stored c" if split == ALL else f"the {split} split's stored c"
    return ids, None, f"{what}, {len(ids)} records"


def c_range(store, split: str = "train", quantile: float = 0.01, given=None) -> tuple[float, float]:
    """``(c_min, c_max)`` of the stored ``shadow`` over ``split``: the ``quantile`` and ``1 - quantile``
    quantiles. 0 is the paper's strict min and max; the default 0.01 keeps an estimator's outliers (one record of
    3,200 at c = -39.6 in SynthFaces v2) from setting the range, where the DiFaReli never saw such a c
    (docs/shadow_maps.md: pooled IoU 0.06 -> 0.12). :func:`c_source` says which records (or range) it takes."""
    return c_range_of(store, split, quantile, given)[:2]


def c_range_of(store, split: str = "train", quantile: float = 0.01, given=None) -> tuple[float, float, str]:
    """:func:`c_range` and where it came from (printed and kept in the provenance)."""
    if not 0.0 <= float(quantile) < 0.5:
        raise errors.UserError(f"c_quantile={quantile} is out of range; use a number in [0, 0.5), e.g. 0.01")
    ids, fixed, what = c_source(store, split, given)
    if fixed is not None:
        return fixed[0], fixed[1], what
    c = np.array([encodings.shadow_logit(store.read(r, ["shadow"])) for r in ids])
    errors.check_finite(c, f"shadow c of the {split} split of {store.root}")
    lo, hi = (float(v) for v in np.quantile(c, [quantile, 1.0 - quantile])) if c.size else (0.0, 0.0)
    if hi <= lo:
        raise errors.UserError(f"the {split} split of {store.root} has no spread of shadow c between its {quantile} "
                               f"and {1 - quantile} quantiles ({lo} to {hi}); the difference method needs records "
                               "with and without cast shadows")
    return lo, hi, f"{what}, quantiles {quantile:g} and {1 - quantile:g}"


def keep_mask(store, rid: str, zero_parts: Sequence[str]) -> np.ndarray | None:
    """The stored ``face_mask`` less ``zero_parts`` of the stored ``masks`` (None: nothing to restrict by)."""
    if not zero_parts or not store.available("face_mask"):
        return None
    a = store.read(rid, ["face_mask", "masks"] if store.available("masks") else ["face_mask"])
    keep = np.asarray(a["face_mask"], bool).copy()
    if "masks" in a:
        keep &= ~np.isin(np.asarray(a["masks"]), [encodings.PART_INDEX[p] for p in zero_parts])
    return keep


def relight_pairs(relighter: Relighter, sources: Sequence, c_min: float, c_max: float) -> np.ndarray:
    """Differences ``Y(relit at c_min) - Y(relit at c_max)`` (B, H, W) of sources (``Relighter.source``) relit with
    their own light, through :meth:`Relighter.relight_many` (one inversion per record, shared by its two c) in
    float: the maps are cut near 0.02, where a uint8 step (0.004) would move them."""
    targets = [Targets.of([s.arrays["light"]] * 2, [c_max, c_min], f"own light of {s.what}") for s in sources]
    y = imageops.luminance(relighter.relight_many(sources, targets, as_float=True).astype(np.float64))
    return y[:, 1] - y[:, 0]


@dataclass
class ShadowMapReport:
    name: str                 # shadow_map@<version>
    raw: str                  # shadow_map@diffraw-<hash>
    c_min: float
    c_max: float
    threshold: float
    relit: int                # records relit in this run (the rest were resumed)
    written: int
    seconds: float
    c_source: str = ""        # which records (or which given / recorded range) c_min and c_max came from

    @property
    def images_per_second(self) -> float:
        return 2 * self.relit / self.seconds if self.seconds > 0 else float("nan")


def compute(model, store, spec, *, provenance: Mapping[str, Any], ids: Sequence[str] | None = None,
            split: str = "train", c_quantile: float = 0.01, threshold: str | float = "relative",
            relative: float = RELATIVE, centre: str = "median", median: int | str = "auto",
            zero_parts: Sequence[str] = ZERO_PARTS, min_contrast: float | None = None,
            min_coherence: float | None = None,
            batch_size: int = 8, version: str | None = None, runtime=None, mean_matching: bool = True,
            device="cpu", progress: bool = True, c_range=None, check_after: int = CHECK_AFTER) -> ShadowMapReport:
    """The whole difference pipeline over ``ids`` (default: every record); writes two derived versions.
    ``min_contrast`` / ``min_coherence`` None: the judge's defaults. ``c_range``: ``(c_min, c_max)`` to relight at
    instead of
    ``split``'s. The DiFaReli's response is checked once ``check_after`` records are relit (0: only at the end), so
    a model that will be refused is refused in minutes, not after the whole store. The store is locked for the
    run: a second concurrent writer is refused, naming this one."""
    if "shadow" not in model_inputs(model):
        raise errors.UserError(f"the difference method relights at two shadow strengths c, but this model consumes "
                               f"{model_inputs(model)} (no 'shadow'); give a DiFaReli checkpoint (model=difareli)")
    threshold, centre = check_threshold(threshold), check_centre(centre)
    with folder_lock(store.root, "shadow-maps"):
        return _compute(model, store, spec, provenance=provenance, ids=ids, split=split, c_quantile=c_quantile,
                        threshold=threshold, relative=float(relative), centre=centre, median=median,
                        zero_parts=zero_parts, min_contrast=min_contrast, min_coherence=min_coherence,
                        batch_size=batch_size, version=version, runtime=runtime, mean_matching=mean_matching,
                        device=device, progress=progress, given=c_range, check_after=check_after)


def _relighter(model, spec, runtime, device, mean_matching: bool, batch_size: int) -> Relighter:
    """The :class:`Relighter` of a loaded ``model`` (its hyperparameters: the store is checked against them);
    without a ``runtime``, plain fp32 on ``device``."""

    rt = runtime if runtime is not None else {"device": str(device), "precision": "fp32"}
    return Relighter(LoadedCheckpoint.of_module(model), spec, runtime=rt, mean_matching=mean_matching,
                     batch_size=batch_size)


def _face_values(store, raw: str, ids: Sequence[str], zero_parts: Sequence[str], centre: str):
    """The centred differences of ``ids``, their mesh and kept-part masks, and their face masks (mesh and kept)."""
    hits = {r: (np.asarray(store.read(r, ["depth"])["depth"]) != 0) if store.available("depth") else None for r in ids}
    keeps = {r: keep_mask(store, r, zero_parts) for r in ids}
    faces, diffs = {}, {}
    for r in ids:
        d = np.asarray(store.read(r, [raw])[raw], dtype=np.float64)
        f = np.ones(d.shape, bool)
        for x in (hits[r], keeps[r]):
            f = f if x is None else f & x
        faces[r], diffs[r] = f, centred(d, f, centre)
    return diffs, hits, keeps, faces


def check_version_free(store, version: str, settings: Mapping[str, Any]) -> None:
    """``shadow_map@<version>`` is new or was made with these ``settings`` (a resume); a version made with others
    (retrained weights at the same path, another sampler or rule) is refused naming what differs."""
    have = store.derived.get(derived.version_name("shadow_map", version))
    if have is None:
        return
    want = json.loads(json.dumps(dict(settings), default=str))  # as the header stores it
    diff = [k for k in sorted(want) if have.get(k) != want[k]]
    if diff:
        shown = "; ".join(f"{k}: {have.get(k)!r} there, {want[k]!r} now" for k in diff[:3])
        raise errors.UserError(f"version={version}: store {store.root} already has shadow_map@{version} made with "
                               f"other settings ({shown}); give another name (version={version}-2) or version=null "
                               "(named by the settings' hash) and train on it with data.versions={shadow_map: <name>}")


def _compute(model, store, spec, *, provenance, ids, split, c_quantile, threshold, relative, centre, median, zero_parts,
             min_contrast, min_coherence, batch_size, version, runtime, mean_matching, device, progress, given,
             check_after) -> ShadowMapReport:
    ids = list(ids) if ids is not None else store.ids()
    c_min, c_max, source = c_range_of(store, split, c_quantile, given)
    median = median_size(median, int(store.dims["H"]))
    norm_range = encodings.store_c_range(store.store_meta)
    prov = {**dict(provenance), "c_min": c_min, "c_max": c_max, "split": split, "mean_matching": mean_matching,
            "c_quantile": float(c_quantile),
            "difference": "Y(relit at c_min) - Y(relit at c_max), own light"}
    if given is not None or split == ALL or (split == "train" and not store.ids(split="train")):
        prov["c_source"] = source  # not the train split's records: said so (the default's versions are unchanged)
    # The global threshold depends on which records it is taken over: another record set is another version.
    chosen = "all" if set(ids) == set(store.ids()) else derived.content_version("ids", {"ids": sorted(ids)}, 12)
    rule = {"threshold": threshold, "relative": relative if threshold == "relative" else None, "centre": centre,
            "median": int(median), "records": chosen}
    if version:  # a name of the user's: checked before any relight, not after every record is relit
        check_version_free(store, version, {**prov, **rule})
    version = version or derived.content_version("diff", {**prov, **rule})
    raw = derived.declare(store, "shadow_map", derived.content_version("diffraw", prov),
                          {**prov, "stage": "raw difference"})
    todo = derived.missing(store, raw, ids)
    relighter = _relighter(model, spec, runtime, device, mean_matching, batch_size)
    start = time.perf_counter()
    step = provenance.get("global_step")
    early = check_after > 0 and len(ids) > check_after  # a check on part of the records, before the rest are relit
    bar = tqdm(total=len(todo), desc="difference maps", disable=not progress)
    for i in range(0, len(todo), batch_size):
        if early and len(ids) - (len(todo) - i) >= check_after:  # records relit so far, resumed ones included
            early = False
            rest = set(todo[i:])
            done = [r for r in ids if r not in rest]
            d, _, _, f = _face_values(store, raw, done, zero_parts, centre)
            judge(measure(list(d.values()), list(f.values()), threshold, relative), min_contrast, min_coherence, step,
                  f" (measured on the first {len(done)} of {len(ids)} records, before relighting the rest; "
                  f"their raw differences are kept in {raw}, which a rerun resumes)")
        chunk = todo[i:i + batch_size]
        srcs = [relighter.source(store, r) for r in chunk]  # with the store's c range: its target maps
        for rid, d in zip(chunk, relight_pairs(relighter, srcs, c_min, c_max)):
            derived.write(store, rid, raw, d.astype(np.float32), overwrite=True)
        bar.update(len(chunk))
        bar.set_postfix(img_s=f"{2 * (i + len(chunk)) / max(time.perf_counter() - start, 1e-9):.2f}")
    bar.close()
    seconds = time.perf_counter() - start
    diffs, hits, keeps, faces = _face_values(store, raw, ids, zero_parts, centre)
    resp = measure(list(diffs.values()), list(faces.values()), threshold, relative)
    judge(resp, min_contrast, min_coherence, step)
    thr = resp.threshold
    final = {**prov, **rule, "threshold": thr, "threshold_rule": resp.rule, "raw": raw, "n_records": len(ids),
             "zero_parts": list(zero_parts), "response_p99": round(resp.p99, 6), "contrast": round(resp.contrast, 6),
             "coherence": round(resp.coherence, 4), "candidates": round(resp.candidates, 4),
             "c_norm_range": list(norm_range) if norm_range else "fixed"}
    try:
        name = derived.declare(store, "shadow_map", version, final)
    except ValueError as e:
        raise errors.UserError(f"{e} (e.g. version=difference-2)") from None
    written = 0
    for r in ids:
        c = encodings.shadow_logit(store.read(r, ["shadow"]))
        m = finish_map(diffs[r], thr, median, c, hits[r], keeps[r], norm_range)
        written += derived.write(store, r, name, m, overwrite=True)
    return ShadowMapReport(name, raw, c_min, c_max, thr, len(todo), written, seconds, source)
