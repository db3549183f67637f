"""Teacher pairs for the single-shot student (``difareli-teacher-pairs``): the teacher relights every training
record toward another record's light, in batches through the relighting core, and each pair is written atomically
into a pair store (an :class:`~difareli.data.store.EncodingStore`) that :class:`difareli.lit.pairs.TeacherPairs` reads;
a rerun skips the pairs already there.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm.auto import tqdm

from difareli.data import encodings as enc
from difareli.data import provenance
from difareli.errors import UserError, check_choice, check_record
from difareli.utils.fileio import folder_lock
from difareli.lit.pairs import LIGHT_FROM_KEY, SOURCE_KEY
from difareli.relight.targets import Targets
from difareli.render.sun_fit import TARGET_SUNS
from difareli.data.provenance import store_identity
from difareli.data.store import EncodingStore


def pair_id(source: str, k: int) -> str:
    return f"{source}__p{k}"


def draw_light_records(ids: Sequence[str], per_record: int, seed: int) -> dict[str, list[str]]:
    """For each record, ``per_record`` other records (uniform, seeded) whose light becomes its target.

    Drawn all at once from ``seed``, so a resumed run draws exactly the same pairs."""
    rng = np.random.default_rng(seed)
    ids = list(ids)
    if len(ids) < 2:
        raise UserError(f"teacher pairs need >= 2 training records to take target lights from; got {len(ids)}")
    out = {}
    for i, rid in enumerate(ids):
        draws = rng.integers(0, len(ids) - 1, size=per_record)
        out[rid] = [ids[j + (j >= i)] for j in draws]  # skip the record itself
    return out


def generate_teacher_pairs(relighter, store: EncodingStore, out: str | Path, *, split: str = "train",
                           per_record: int = 1, limit: int | None = None, batch_size: int = 8, seed: int = 0,
                           progress: bool = True, stop_after: int | None = None,
                           target_sun: str = "shadows") -> dict[str, Any]:
    """Relight every ``split`` record of ``store`` toward another random record's light with the teacher in
    ``relighter`` (a :class:`~difareli.relight.relighter.Relighter`), ``batch_size`` images per batched relight;
    write each pair atomically into the pair store at ``out`` and skip pairs already there (resume).

    ``out`` is locked for the run, and its ``provenance.json`` ties it to the source store and the teacher's
    weights (sampler, precision, split, seed, target sun): a rerun with another teacher or store is refused,
    naming what differs. ``target_sun``: where a target shadow map is marched (``render.sun_fit.TARGET_SUNS``:
    toward the key sun found from the cast shadows of the record whose light it is, as the benchmark and the
    relight do, or its radiance peak); each pair's direction is in its meta. ``stop_after`` ends after that many
    new pairs (tests simulate a kill with it). Returns counts and pairs/s.
    """
    with folder_lock(out, "teacher-pairs"):
        return _generate(relighter, store, out, split=split, per_record=per_record, limit=limit,
                         batch_size=batch_size, seed=seed, progress=progress, stop_after=stop_after,
                         target_sun=check_choice(target_sun, "target_sun", TARGET_SUNS))


def pair_provenance(relighter, store: EncodingStore, *, split: str, seed: int, per_record: int,
                    target_sun: str = "shadows") -> dict[str, Any]:
    """What makes a teacher-pair store: the source store, the teacher's weights and how they relit (the relighter's
    identity, its weights under ``teacher``)."""
    how = relighter.identity()
    return {"kind": "teacher_pairs", "source_store": store_identity(store), "teacher": how.pop("checkpoint"), **how,
            "split": split, "seed": int(seed), "per_record": int(per_record),
            **({"target_sun": target_sun} if "shadow_map" in relighter.model_inputs else {})}


def _generate(relighter, store: EncodingStore, out: str | Path, *, split: str, per_record: int, limit: int | None,
              batch_size: int, seed: int, progress: bool, stop_after: int | None, target_sun: str) -> dict[str, Any]:
    inputs = relighter.model_inputs
    dependent = enc.light_dependent(inputs)
    ids = store.ids(split=split) or []
    if not ids:
        raise UserError(f"store {store.root} has no records in split {split!r}; set split=<one of its splits>")
    draws = draw_light_records(ids, per_record, seed)
    todo = [(rid, k, lid) for rid in ids for k, lid in enumerate(draws[rid])]
    if limit is not None:
        todo = todo[:int(limit)]
    has_c = store.available("shadow")
    names = list(dict.fromkeys(["image", "light", *(["shadow"] if has_c else []), *dependent]))
    done = (Path(out) / "store.json").is_file() and bool(EncodingStore.open(out).ids())
    provenance.ensure(out, pair_provenance(relighter, store, split=split, seed=seed, per_record=per_record,
                                           target_sun=target_sun),
                      "teacher pairs", has_results=done)
    pairs = EncodingStore.create(out, store.dims, names, meta={"kind": "teacher_pairs", "source_store": str(store.root),
                                                              "split": split, "seed": seed, "per_record": per_record},
                                 durable=True)
    left = [t for t in todo if not pairs.has(pair_id(t[0], t[1]))]
    done_before, written, start = len(todo) - len(left), 0, time.perf_counter()
    bar = tqdm(total=len(todo), initial=done_before, desc="teacher pairs", disable=not progress, unit="pair")
    for b in range(0, len(left), batch_size):
        batch = left[b:b + batch_size]
        if stop_after is not None:
            batch = batch[:max(0, stop_after - written)]
        if not batch:
            break
        srcs = [relighter.source(store, rid) for rid, _, _ in batch]
        lights = [check_record(store.read(lid, ["light"] + (["shadow"] if has_c else [])), lid, store.root)
                  for _, _, lid in batch]
        found = [relighter.key_sun(relighter.source(store, lid)) if target_sun == "shadows" else None
                 for _, _, lid in batch]
        suns = [None if f is None else f.direction for f in found]
        targets = Targets.of([l["light"] for l in lights], [enc.shadow_logit(l) for l in lights], "teacher targets",
                             suns=suns)
        # Source k under target k: one batched inversion and decode; NaN refused there.
        relit = relighter.relight_many(srcs, [targets.take(k, k + 1) for k in range(len(srcs))])[:, 0]
        tgts = [targets.retarget(s.arrays, inputs, k, k + 1)[0] for k, s in enumerate(srcs)]
        for (rid, k, lid), img, light, tgt, sun in zip(batch, relit, lights, tgts, suns):
            arrays = {**{n: tgt[n] for n in dependent}, "image": img,
                      "light": light["light"], **({"shadow": light["shadow"]} if has_c else {})}
            meta = {SOURCE_KEY: rid, LIGHT_FROM_KEY: lid, "split": split, "subject": store.meta(rid).get("subject"),
                    "shadow": enc.shadow_logit(light), **({} if sun is None else {"sun": [float(v) for v in sun]})}
            pairs.write(pair_id(rid, k), {n: arrays[n] for n in names}, meta)
            written += 1
        bar.update(len(batch))
    bar.close()
    seconds = time.perf_counter() - start
    rate = written / seconds if seconds > 0 else float("nan")
    print(f"teacher pairs: {written} new, {done_before} already in {out}, {len(todo)} planned; {rate:.3f} pairs/s")
    return {"written": written, "skipped": done_before, "planned": len(todo), "pairs_per_s": rate,
            "seconds": seconds, "store": pairs}
