"""SynthFaces: procedural faces rendered under known lights, with every encoding as ground truth, written into an
encodings store (resumable, sharded, in worker processes). A subject and its image formation: ``synth/subject.py``;
what defines a store: ``synth/config.py``."""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from difareli.utils.fileio import RESUME, on_full_disk
from difareli.utils.processes import die_with_parent
from difareli.render import cast_shadows
from difareli.data.shard import select as shard_select
from difareli.data.store import EncodingStore
from difareli.data import protocols as sp
from difareli.synth.blas import single_thread_blas
from difareli.synth.config import IDENTITY_DIM, ConfigError, SynthConfig
from difareli.synth.lights import add_suns, extra_sun_rng, light_rng, sample_light
from difareli.synth.subject import build_subject, estimation_images, shade
from difareli.synth.c_norm import finalise
from difareli.synth.estimated import missing_estimators


def render_records(k: int, light_indices: list[int], cfg: SynthConfig, split: str) -> Iterator[tuple[str, dict, dict]]:
    """Yield ``(record_id, arrays, meta)`` for subject ``k`` under each light in ``light_indices``."""
    subject = build_subject(k, cfg)
    group = sp.light_group(k, cfg.light_group_size)
    lights = [sample_light(light_rng(cfg.seed, group, j)) for j in light_indices]
    fx = cfg.fx
    if fx.multi_sun:
        lights = [add_suns(light, extra_sun_rng(cfg.seed, group, j)) for j, light in zip(light_indices, lights)]
    # One cast-shadow pass per sun of every light, in one call (the BVH is built once per subject).
    dirs = [d for light in lights for d, _ in light.suns()]
    maps = list(cast_shadows(subject.scene, subject.gbuffer, np.array(dirs))) if dirs else []

    big = estimation_images(k, lights, cfg)
    for i, (j, light) in enumerate(zip(light_indices, lights)):
        k_suns = len(light.suns())
        casts, maps = maps[:k_suns], maps[k_suns:]
        arrays, fx_meta = shade(subject, light, casts, cfg, None if big is None else big[i])
        meta = {"subject": sp.subject_name(k), "light_index": j, "light_group": group, "split": split,
                "source": "synthfaces", "c": float(arrays["shadow"][0]), **light.meta(), **subject.meta,
                "realism": cfg.realism, "effects": fx.as_dict(), "inputs": cfg.inputs, **fx_meta}
        yield sp.record_id(k, j), arrays, meta



# ------------------------------------------------------------------------------------------ data set
def _open_store(out_dir: str, cfg: SynthConfig, durable: bool) -> EncodingStore:
    dims = {"H": cfg.resolution, "W": cfg.resolution, "S": _shape_dim(), "D": IDENTITY_DIM}
    want = cfg.header_meta()
    if os.path.exists(os.path.join(out_dir, "store.json")):
        store = EncodingStore.open(out_dir, writable=True, durable=durable)
        have = store.store_meta
        if have.get("synthfaces_version") is None:
            old = 2 if "inputs" in have else 1
            raise ConfigError(
                f"store {out_dir} is a SynthFaces v{old} store (it still opens for reading); this generator writes v3 "
                f"records and does not add them to it. Regenerate into a new folder: difareli-synth out_dir=<new dir> "
                f"subjects={cfg.subjects} lights={cfg.lights} resolution={cfg.resolution} seed={cfg.seed} "
                f"realism={cfg.realism} inputs={cfg.inputs}")
        diff = {k: (have.get(k), v) for k, v in want.items() if have.get(k) != v}
        if diff:
            raise ConfigError(f"store {out_dir} was generated with a different configuration "
                             f"(key: (existing, requested)) {diff}; use a new out_dir to generate this one")
        # Same configuration: the header keeps what generation added to it (the v3 c range).
        return EncodingStore.create(out_dir, dims, cfg.encodings, None, durable=durable)
    return EncodingStore.create(out_dir, dims, cfg.encodings, want, durable=durable)


def _shape_dim() -> int:
    from difareli.render.face_model import SHAPE_DIM

    return int(SHAPE_DIM)


def _work(args) -> int:
    # Pool task: render one subject's missing lights and write them; returns the number written.
    out_dir, cfg, k, todo, split, durable = args
    store = EncodingStore.open(out_dir, durable=durable)
    with single_thread_blas():
        return sum(bool(store.write(rid, arrays, meta)) for rid, arrays, meta in render_records(k, todo, cfg, split))


@dataclass
class GenerateReport:
    written: int
    skipped: int
    seconds: float
    problems: list[str]

    @property
    def images_per_second(self) -> float:
        return self.written / self.seconds if self.seconds > 0 else 0.0


def generate(out_dir: str, subjects: int, lights: int, resolution: int, seed: int = 0, *, workers: int = 1,
             durable: bool = False, progress: Callable[[int, int], None] | None = None,
             shard: str | None = None, **options) -> GenerateReport:
    """Generate (or complete) the data set in ``out_dir``; existing records are skipped.

    ``options`` are the other :class:`SynthConfig` fields (``light_group_size``, ``splits``, ...).
    ``workers > 1`` renders subjects in a process pool; results do not depend on it.
    ``durable`` fsyncs every file (atomicity against a killed run does not need it: records are renamed
    into place whole either way). ``shard="i/n"`` renders only the subjects of that shard (``difareli.data.shard``);
    shards may run concurrently into one ``out_dir``. A full disk is one line naming the file (records already
    written are whole: rerun to resume), with no partial record or scratch file left.
    """
    with on_full_disk(out_dir, scratch=[out_dir], fix=RESUME):
        return _generate(out_dir, subjects, lights, resolution, seed, workers=workers, durable=durable,
                         progress=progress, shard=shard, **options)


def _generate(out_dir: str, subjects: int, lights: int, resolution: int, seed: int, *, workers: int, durable: bool,
              progress: Callable[[int, int], None] | None, shard: str | None, **options) -> GenerateReport:
    cfg = SynthConfig(subjects=subjects, lights=lights, resolution=resolution, seed=seed, **options)
    try:
        splits = sp.assign_splits(cfg.subjects, cfg.splits, cfg.light_group_size, cfg.seed)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if cfg.splits.get("test", 0) > 0 and not splits["test"]:  # a training-only store is fine, but said
        import warnings

        groups = -(-cfg.subjects // cfg.light_group_size)
        warnings.warn(f"subjects={cfg.subjects} make {groups} light group(s) of {cfg.light_group_size}, too few for a "
                      "test split (3 or more): the store has no evaluation pairs, so difareli-benchmark cannot "
                      "score on it; give subjects=8 or more for one", UserWarning, stacklevel=2)
    if cfg.inputs == "estimated":
        if why := missing_estimators():
            raise ConfigError(why)
    store = _open_store(out_dir, cfg, durable)
    split_of = sp.split_of(splits)
    existing = set(store.ids())
    tasks, skipped = [], 0
    mine = shard_select(range(cfg.subjects), shard, key=sp.subject_name)  # a subject's lights stay together
    for k in mine:
        todo = [j for j in range(cfg.lights) if sp.record_id(k, j) not in existing]
        skipped += cfg.lights - len(todo)
        if todo:
            tasks.append((out_dir, cfg, k, todo, split_of[k], durable))
    total = sum(len(t[3]) for t in tasks)
    t0 = time.perf_counter()
    written = 0
    if tasks:
        if workers > 1 and len(tasks) > 1:
            # Build the face model and head template once here; forked workers inherit them (~1-5 s each).
            from difareli.synth.accessories import _template

            _template()
            ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else None
            # Workers die with this process (SIGKILL included) instead of lingering as orphans.
            with ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=ctx,
                                     initializer=die_with_parent, initargs=(os.getpid(),)) as pool:
                for n in pool.map(_work, tasks, chunksize=1):
                    written += n
                    if progress:
                        progress(written, total)
        else:
            for t in tasks:
                written += _work(t)
                if progress:
                    progress(written, total)
    seconds = time.perf_counter() - t0
    with on_full_disk(f"{out_dir}/{sp.SPLITS_FILE}, {sp.PROTOCOLS_FILE}", scratch=[out_dir], fix=RESUME):
        sp.write_split_files(out_dir, splits, cfg.lights, cfg.light_group_size, cfg.seed)
    store.refresh()
    missing = [sp.record_id(k, j) for k in mine for j in range(cfg.lights)
               if not store.has(sp.record_id(k, j))]
    problems = [f"{rid}: missing" for rid in missing]
    if cfg.inputs == "estimated" and not problems and len(store.ids()) == cfg.subjects * cfg.lights:
        with on_full_disk(f"{out_dir}/store.json (the c range) and the records' shadow maps", scratch=[out_dir],
                          fix="free space and rerun the same command to finish scaling the maps"):
            finalise(store, cfg.c_quantile)  # every record is there: the train split's c range, maps scaled by it
    return GenerateReport(written, skipped, seconds, problems)
