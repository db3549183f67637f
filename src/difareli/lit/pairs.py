"""Relit pairs for the single-shot student (DiFaReli++_ss): the pair samplers and how a teacher-pair
store is read.

A pair is a source record, a target light (and shadow logit c') and the image under it. The student's
DataModule (``data.pairs``) serves pairs from one of the samplers of :data:`PAIR_SAMPLERS`:

- ``teacher``: a teacher-pair store written by ``difareli-teacher-pairs``
  (:func:`difareli.jobs.teacher_pairs.generate_teacher_pairs`);
- ``gt``: SynthFaces ground truth: the same subject under another light index (that record's image is exact);
  its target light is fitted on that record (``gt_light=subject``) or on any record of its light group under the
  same light index (``gt_light=group``: another face's fit of the same true light half the time with groups of
  two, as protocol (ii) gives the model at test time);
- ``mix``: both, concatenated (each epoch sees every teacher pair and every ground-truth source once);
- ``gt_shadow``: ground-truth pairs and :class:`ShadowPairs` concatenated: a shadowed record under its own light
  with its cast shadows taken away or given back, so the target shadow map alone tells the image what changes;
- ``identity``: the record itself (target = source), a sanity check.

A teacher-pair store is an :class:`~difareli.data.store.EncodingStore` whose records hold the relit ``image``, the
target ``light`` and ``shadow`` (c'), and the target's light-dependent encodings (re-rendered through the
registry, e.g. the ray-marched shadow map); its per-record meta names the ``source`` and ``light_from`` records.
Every item's target condition is the source's encodings with the light-dependent ones replaced: exactly what
:func:`difareli.render.retarget.retarget` gives at inference time.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from torch.utils.data import ConcatDataset, Dataset

from difareli.data import encodings as enc
from difareli.data.inputs import image_to_tensor, prepare_nonspatial, prepare_spatial, read_record, relight_reads
from difareli.errors import UserError, check_record
from difareli.evaluation.map_response import shadowed_records
from difareli.data.store import EncodingStore
from difareli.render.retarget import retarget
from difareli.data.provenance import PROVENANCE, store_identity

#: Meta keys of a teacher-pair record: the input record and the record the target light was taken from.
SOURCE_KEY, LIGHT_FROM_KEY = "source", "light_from"


def target_arrays(src: Mapping[str, np.ndarray], names: Sequence[str], light: np.ndarray,
                  shadow: float | None) -> dict[str, np.ndarray]:
    """The source's ``names`` under a target light: light-dependent ones re-rendered (the registry), rest kept."""
    return {**src, **retarget(src, list(names), np.asarray(light, dtype=np.float64), shadow)}


class PairDataset(Dataset):
    """Base: source ``image``/``spatial``/``nonspatial`` and ``target_image``/``target_spatial``/
    ``target_nonspatial`` tensors per item; ``ids`` are the source records (the non-spatial statistics)."""

    def __init__(self, store: EncodingStore, ids: Sequence[str], spatial: Sequence[str], nonspatial: Sequence[str]):
        self.store, self.ids = store, list(ids)
        self.spatial, self.nonspatial = list(spatial), list(nonspatial)
        self.inputs = [*self.spatial, *self.nonspatial]
        self.dependent = enc.light_dependent(self.inputs)
        # What a target condition re-rendered from the source needs: its light, c and the registry's `needs`.
        self.names = list(dict.fromkeys([*relight_reads(self.inputs)]
                                        + (["shadow"] if store.available("shadow") else [])))
        missing = [n for n in self.names if not store.available(n)]
        if missing:
            raise UserError(f"student pairs need encoding(s) {missing}, which the store at {store.root} lacks; "
                            "use a store that has them (SynthFaces, or difareli-preprocess with those estimators)")

    def __len__(self) -> int:
        return len(self.ids)

    def source(self, rid: str) -> dict[str, np.ndarray]:
        return read_record(self.store, rid, self.names)

    def item(self, rid: str, src: Mapping[str, np.ndarray], tgt: Mapping[str, np.ndarray],
             target_image: np.ndarray) -> dict[str, Any]:
        return {"image": image_to_tensor(src["image"]), "spatial": prepare_spatial(self.spatial, src),
                "nonspatial": prepare_nonspatial(self.nonspatial, src), "record_id": rid,
                "target_image": image_to_tensor(target_image), "target_spatial": prepare_spatial(self.spatial, tgt),
                "target_nonspatial": prepare_nonspatial(self.nonspatial, tgt)}


class IdentityPairs(PairDataset):
    """Target = source: the record under its own light (its own stored encodings, not re-rendered)."""

    def __getitem__(self, i: int) -> dict[str, Any]:
        rid = self.ids[i]
        src = self.source(rid)
        return self.item(rid, src, src, src["image"])


#: data.gt_light: whose fitted light conditions a ground-truth pair's target (see the module docstring).
GT_LIGHTS = ("subject", "group")
#: data.gt_maps: a ground-truth pair's target shadow map: ``march``, re-rendered on the source's depth by the relight's
#: maker (what a relight gives at test time); ``stored``, the target record's own stored ``shadow_map`` (with
#: ``data.versions.shadow_map=visible``: the exact shadow its image shows, so map and image agree, as the teacher's
#: training maps did). Same subject, same geometry: the target's map lies on the source's face.
GT_MAPS = ("march", "stored")


class GroundTruthPairs(PairDataset):
    """SynthFaces: the target is another light index of the same subject, drawn anew at every visit; its
    light (the stored one, estimated in v2 stores) and c re-render the source's light-dependent encodings.
    ``light_from="group"``: light and c come from a record drawn among those of the target's light group and
    light index (the same true light, each fitted on its own face), so the student meets the fitting errors of
    other faces' lights, as in protocol (ii), while the image it learns is still the exact target."""

    def __init__(self, store, ids, spatial, nonspatial, light_from: str = "subject", with_source: bool = False,
                 target_maps: str = "march"):
        super().__init__(store, ids, spatial, nonspatial)
        if light_from not in GT_LIGHTS:
            raise UserError(f"data.gt_light={light_from!r} is not one of {list(GT_LIGHTS)}")
        if target_maps not in GT_MAPS:
            raise UserError(f"data.gt_maps={target_maps!r} is not one of {list(GT_MAPS)}")
        self.stored_maps = target_maps == "stored" and "shadow_map" in self.inputs
        meta = {rid: store.meta(rid) for rid in store.ids()}  # read once: the maps below consult it per pair
        by_subject: dict[Any, list[str]] = {}
        by_light: dict[Any, list[str]] = {}
        for rid, m in meta.items():
            by_subject.setdefault(m.get("subject"), []).append(rid)
            by_light.setdefault((m.get("light_group"), m.get("light_index")), []).append(rid)
        # with_source: the source's own light index is a target too (the identity pair, relit under its own
        # light), so that a student learns to give its input back when the light does not change.
        self.others = {r: [o for o in by_subject.get(meta[r].get("subject"), []) if o != r or with_source]
                       for r in self.ids}
        # Target record -> the records whose fitted light may stand for its light (itself included).
        self.light_records = {o: (by_light[(meta[o].get("light_group"), meta[o].get("light_index"))]
                                  if light_from == "group" and meta[o].get("light_group") is not None
                                  else [o]) for r in self.ids for o in self.others[r]}
        alone = [r for r, o in self.others.items() if not [x for x in o if x != r] or meta[r].get("subject") is None]
        if alone:
            raise UserError(f"data.pairs=gt: {len(alone)} record(s) of {store.root} (e.g. {alone[:3]}) have no other "
                            "record of the same subject (the ground truth); use a SynthFaces store with lights >= 2, "
                            "or data.pairs=teacher")

    def __getitem__(self, i: int) -> dict[str, Any]:
        rid = self.ids[i]
        others = self.others[rid]
        tid = others[int(torch.randint(len(others), (1,)))]  # seeded per worker by Lightning
        # The identity pair is conditioned on the source's own light: relit under its own light, the input comes
        # back (another face's fit of that light would teach the student to ignore small light changes).
        lights = self.light_records[tid] if tid != rid else [tid]
        lid = lights[int(torch.randint(len(lights), (1,)))] if len(lights) > 1 else tid
        src = self.source(rid)
        light_names = ["light"] + (["shadow"] if "shadow" in src else [])
        # One read when the target's own fit conditions it (always with gt_light=subject).
        tgt_rec = check_record(self.store.read(tid, ["image"] + (light_names if lid == tid else [])
                                               + (["shadow_map"] if self.stored_maps else [])), tid, self.store.root)
        light = tgt_rec if lid == tid else check_record(self.store.read(lid, light_names), lid, self.store.root)
        tgt = target_arrays(src, self.inputs, light["light"], enc.shadow_logit(light))
        if self.stored_maps:
            tgt["shadow_map"] = tgt_rec["shadow_map"]
        return self.item(rid, src, tgt, tgt_rec["image"])


#: A record takes part in :class:`ShadowPairs` when its visible shadows cover at least this share of its face.
SHADOW_PAIR_SHARE = 0.02


class ShadowPairs(PairDataset):
    """SynthFaces v3, one light: a shadowed record's cast shadows taken away (the target: the same light rendered
    with no cast shadow, ``image_unshadowed_gt``, c at the strength scale's floor and a zero map) or given back (the
    source: that image with a zero map and that c; the target: the record itself with its own map), one of the two
    at random at every visit. Light and geometry do not change, so only the map (and c) tells the student what to
    draw: what relighting at a fixed light with another shadow strength asks of it, and what
    ``evaluation.map_response`` measures."""

    def __init__(self, store, ids, spatial, nonspatial, min_share: float = SHADOW_PAIR_SHARE):
        super().__init__(store, ids, spatial, nonspatial)
        if not store.available("image_unshadowed_gt") or "shadow_map" not in self.inputs:
            raise UserError(f"shadow pairs need image_unshadowed_gt (SynthFaces v3 from 2026-12-07: regenerate the "
                            f"store with difareli-synth) and a shadow_map input; the store at {store.root} or the "
                            "model lacks them; or use data.pairs=gt")
        self.ids = shadowed_records(store, self.ids, min_share)
        if not self.ids:
            raise UserError(f"no record of {store.root} has visible cast shadows on {min_share:.0%} of its face")

    def __getitem__(self, i: int) -> dict[str, Any]:
        rid = self.ids[i]
        src = self.source(rid)
        free = {**src, "image": check_record(self.store.read(rid, ["image_unshadowed_gt"]), rid,
                                             self.store.root)["image_unshadowed_gt"],
                "shadow_map": np.zeros_like(src["shadow_map"])}
        if "shadow" in src:
            free["shadow"] = np.full_like(src["shadow"], enc.SHADOW_C_LO)
        if int(torch.randint(2, (1,))):  # taken away
            return self.item(rid, src, free, free["image"])
        return self.item(rid, free, src, src["image"])  # given back


def check_pair_source(pair_store: EncodingStore, store: EncodingStore) -> None:
    """A teacher-pair store must come from this training store (its provenance, or for pair stores written
    before provenance was recorded, the source path in its header)."""
    prov = Path(pair_store.root) / PROVENANCE
    if prov.is_file():
        made_from = json.loads(prov.read_text()).get("source_store")
        ok, have = made_from == store_identity(store), f"a store with identity {made_from}"
    else:
        made_from = pair_store.store_meta.get("source_store")
        ok = made_from is not None and Path(made_from).resolve() == Path(store.root).resolve()
        have = f"store {made_from}"
    if not ok:
        raise UserError(f"teacher-pair store {pair_store.root} was made from {have}, not from the training store "
                        f"{store.root} ({store_identity(store)}); give the pair store made from it "
                        f"(difareli-teacher-pairs store={store.root} out=<new folder>)")


class TeacherPairs(PairDataset):
    """Pairs of a teacher-pair store whose sources are among ``ids`` (the split's records)."""

    def __init__(self, store, ids, spatial, nonspatial, pair_store: EncodingStore):
        super().__init__(store, ids, spatial, nonspatial)
        missing = [n for n in ["image", "light", *self.dependent] if not pair_store.available(n)]
        if missing:
            raise UserError(f"teacher-pair store {pair_store.root} lacks {missing} (the student's target "
                            "encodings); regenerate it with difareli-teacher-pairs model=<this student's variant>")
        check_pair_source(pair_store, store)
        wanted = set(self.ids)
        self.pair_store = pair_store
        self.pairs = [p for p in pair_store.ids() if pair_store.meta(p).get(SOURCE_KEY) in wanted]
        self.ids = [pair_store.meta(p)[SOURCE_KEY] for p in self.pairs]

    def __getitem__(self, i: int) -> dict[str, Any]:
        pid, rid = self.pairs[i], self.ids[i]
        src = self.source(rid)
        pair = check_record(self.pair_store.read(pid, ["image", *self.dependent]), pid, self.pair_store.root)
        tgt = {**src, **{k: pair[k] for k in self.dependent}}
        return self.item(rid, src, tgt, pair["image"])


def _concat(parts: Sequence[PairDataset]) -> ConcatDataset:
    """The pair datasets one after the other; ``ids``: their sources, in the same order."""
    out = ConcatDataset(parts)
    out.ids = [rid for part in parts for rid in part.ids]
    return out


def _mixed(store, ids, spatial, nonspatial, pair_store: EncodingStore, gt: Mapping[str, Any] | None = None):
    """Teacher pairs and ground-truth pairs together."""
    return _concat([TeacherPairs(store, ids, spatial, nonspatial, pair_store),
                    GroundTruthPairs(store, ids, spatial, nonspatial, **dict(gt or {}))])


def _needs_pair_store(make_with: Callable) -> Callable:
    def make(store, ids, spatial, nonspatial, pair_store, gt=None):
        if pair_store is None:
            raise UserError("data.pairs=teacher|mix needs data.teacher_pairs=<store written by difareli-teacher-pairs>")
        return make_with(store, ids, spatial, nonspatial, pair_store, gt)

    return make


#: data.pairs -> dataset factory ``(store, ids, spatial, nonspatial, pair_store, gt) -> Dataset`` (``gt``: the
#: options of :class:`GroundTruthPairs`).
PAIR_SAMPLERS: dict[str, Callable[..., Dataset]] = {
    "teacher": _needs_pair_store(lambda store, ids, sp, ns, ps, gt: TeacherPairs(store, ids, sp, ns, ps)),
    "gt": lambda store, ids, sp, ns, pair_store=None, gt=None: GroundTruthPairs(store, ids, sp, ns, **dict(gt or {})),
    "mix": _needs_pair_store(_mixed),
    "gt_shadow": lambda store, ids, sp, ns, pair_store=None, gt=None: _concat(
        [GroundTruthPairs(store, ids, sp, ns, **dict(gt or {})), ShadowPairs(store, ids, sp, ns)]),
    "identity": lambda store, ids, sp, ns, pair_store=None, gt=None: IdentityPairs(store, ids, sp, ns),
}


def pair_dataset(kind: str, store: EncodingStore, ids: Sequence[str], spatial: Sequence[str],
                 nonspatial: Sequence[str], pair_store: EncodingStore | None = None,
                 gt_light: str = "subject", gt_identity: bool = False, gt_maps: str = "march") -> Dataset:
    """The ``kind`` pair sampler (``data.pairs``) over the records ``ids``; ``gt_light``: see :data:`GT_LIGHTS`;
    ``gt_identity``: ground-truth targets include the source's own light index (the identity pair); ``gt_maps``:
    see :data:`GT_MAPS`."""
    if kind not in PAIR_SAMPLERS:
        raise UserError(f"data.pairs={kind!r} is not a pair sampler; choose one of {sorted(PAIR_SAMPLERS)}")
    return PAIR_SAMPLERS[kind](store, ids, spatial, nonspatial, pair_store,
                               {"light_from": gt_light, "with_source": bool(gt_identity), "target_maps": gt_maps})
