"""Preprocessing a folder (``difareli-preprocess``): one store record per image, a preview and a report entry each,
in this process or in ``workers`` processes.

The estimators in worker processes (``difareli-preprocess workers=n``): each worker builds the same pipeline
once (``Pipeline.config``) and processes whole images, one at a time, with one BLAS thread; results come back in
input order and the parent writes the store. Workers die with their parent
(:func:`difareli.utils.processes.die_with_parent`).

Processes, not threads, for whole images: mediapipe's graphs and dlib are not thread-safe, and numpy releases the
GIL only in parts of the work. ``spawn``: a fork would copy a parent's loaded mediapipe/torch thread pools. In one
process (the default) two threads still overlap: a reader decodes and aligns the next photos (the aligner's graphs
are its own) while the estimators run (:mod:`.stream`).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from difareli.utils.fileio import write_json_atomic
from difareli.data.store import EncodingStore
from difareli.errors import UserError

from .loading import BadInput, list_inputs, load_image, record_ids
from .pipeline import PREVIEWS, REPORT, Pipeline
from difareli.data import shard as sharding
from difareli.utils.processes import die_with_parent

_PIPELINE = None
#: Photos whose entries and previews may wait in the preview thread (memory: their arrays and contexts).
PREVIEWS_AHEAD = 4


def _init(parent_pid: int, config: Mapping) -> None:
    global _PIPELINE
    die_with_parent(parent_pid)
    _PIPELINE = Pipeline.from_config(config["estimators"], config["encodings"], **config["kwargs"])


def _work(f: Path, preview: Path | None) -> dict:
    return compute_one(_PIPELINE, f, preview)


def compute_in_workers(pipeline, files: list[Path], preview_dir: Path | None, ids: Mapping[Path, str],
                       workers: int) -> Iterator[dict]:
    """:func:`compute_one` of every file in ``workers`` processes, yielded in ``files`` order."""
    config = getattr(pipeline, "config", None)
    if config is None:
        raise UserError("workers > 1 needs a pipeline built by Pipeline.from_config (its config is rebuilt in "
                        "each worker)")
    n = max(1, min(int(workers), len(files)))
    env = {"OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1"}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)  # the spawned interpreters read them before importing torch / OpenMP
    try:
        pool = ProcessPoolExecutor(n, mp_context=mp.get_context("spawn"), initializer=_init,
                                   initargs=(os.getpid(), config))
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    with pool:
        previews = [None if preview_dir is None else preview_dir / f"{ids[f]}.png" for f in files]
        yield from pool.map(_work, files, previews)


@dataclass
class RunSummary:
    """What one run did; ``entries`` is the report's per-file list."""

    written: int = 0
    skipped: int = 0
    failed: int = 0
    seconds: float = 0.0
    entries: list[dict] = field(default_factory=list)
    stages: dict[str, float] = field(default_factory=dict)  # seconds per stage, summed over written images

    @property
    def images_per_second(self) -> float:
        return self.written / self.seconds if self.seconds > 0 else 0.0

    def stage_ms(self) -> dict[str, float]:
        """Mean milliseconds per written image of each stage (alignment, then one per estimator)."""
        return {k: round(1000 * v / self.written, 1) for k, v in self.stages.items()} if self.written else {}


def compute_one(pipeline: Pipeline, f: Path, preview: Path | None) -> dict:
    """Decode and process one file (and write its preview): ``{"entry", "arrays", "meta", "seconds"}``; a bad
    image or an estimator bug is a failed entry, never an exception."""
    t0 = time.perf_counter()
    try:
        rgb, notes = load_image(f, pipeline.min_side, pipeline.max_side)
        res: tuple | Exception = pipeline.process(rgb)
        extra = {"load_notes": notes, "input_size": list(rgb.shape[:2])}
    except Exception as e:  # noqa: BLE001 - a bad image or an estimator bug must not stop the other images
        res, extra = e, {}
    return finish_one(f, res, extra, preview, time.perf_counter() - t0)


def finish_one(f: Path, res: tuple | Exception, extra: dict, preview: Path | None, seconds: float) -> dict:
    """The report entry (and the preview) of one file from the pipeline's result or exception."""
    out: dict[str, Any] = {}
    try:
        if isinstance(res, Exception):
            raise res
        arrays, meta, ctx = res
        notes = extra["load_notes"] + ctx["notes"]
        meta.update(source_file=f.name, input_size=extra["input_size"], notes=notes, split="predict")
        if preview is not None:
            from .preview import save_preview

            save_preview(preview, ctx)
        entry = {"status": "ok", "notes": notes, "faces": meta["faces"],
                 **{k: meta[k] for k in ("reprojection_px", "bfm_fit", "light_fit") if k in meta}}
        out.update(arrays=arrays, meta=meta)
    except BadInput as e:
        entry = {"status": "failed", "reason": str(e)}
    except Exception as e:  # noqa: BLE001 - an estimator bug must not stop the other images
        entry = {"status": "failed", "reason": f"internal error: {type(e).__name__}: {e}"}
    return {**out, "entry": entry, "seconds": seconds}


def compute_streamed(pipeline: Pipeline, files: list[Path], preview_dir: Path | None, ids: Mapping[Path, str],
                     write: Callable[[Path, dict], None] | None = None) -> Iterator[dict]:
    """:func:`compute_one` of every file, decoding and alignment overlapped with the estimators (:mod:`.stream`),
    yielded in ``files`` order. Each photo's report entry, preview and ``write(f, result)`` (the record, where the
    photo succeeded) run in a third thread while the estimators go on with the next photos: they are a third of a
    photo's time (PNG encoding and file writes, which release the GIL), and in the estimators' thread they would
    be the run's bottleneck. ``result["written"]`` says that ``write`` returned, ``result["write_error"]`` holds
    what it raised."""
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    from .stream import stream

    def load(f: Path):
        return load_image(f, pipeline.min_side, pipeline.max_side)

    def finish(f: Path, res, extra: dict, seconds: float) -> dict:
        t0 = time.perf_counter()
        done = finish_one(f, res, extra, None if preview_dir is None else preview_dir / f"{ids[f]}.png", 0.0)
        if write is not None and done["entry"]["status"] == "ok":
            try:
                write(f, done)
                done["written"] = True
            except Exception as e:  # noqa: BLE001 - reported by the caller, as its own write's error would be
                done["write_error"] = e
        done["seconds"] = seconds + time.perf_counter() - t0
        return done

    pending: deque = deque()
    with ThreadPoolExecutor(1, thread_name_prefix="preprocess-preview") as pool:
        for f, res, extra, seconds in stream(pipeline, files, load):
            pending.append(pool.submit(finish, f, res, extra, seconds))
            while len(pending) > PREVIEWS_AHEAD or (pending and pending[0].done()):
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def announce(f: Path, entry: dict, arrays: Mapping[str, Any], say: Callable[[str], None]) -> None:
    """The console lines of a photo written: where its fitted light comes from (also put in its report ``entry``)
    and the notes that change the result."""
    if "light" in arrays:
        from .light import describe_light

        entry["light_from"] = describe_light(arrays["light"])
        say(f"{f.name}: light {entry['light_from']}")
    for note in entry.get("notes", []):
        if note.startswith(("small face", "grey photo")):
            say(f"{f.name}: {note}")


def run(pipeline: Pipeline, in_dir: str, out_dir: str, *, overwrite: bool = False, previews: bool = True,
        durable: bool = False, progress: bool = True, shard: str | None = None, workers: int = 1,
        overlap: bool = True) -> RunSummary:
    """Process every file of ``in_dir`` (or the single file) into the store at ``out_dir``; never raises
    for a bad image: each gets a report entry and nothing is written for it. ``shard="i/n"`` processes only
    the records of that shard (``difareli.data.shard``; shards may run concurrently into one store) and writes
    its report as ``preprocess_report.shard-i-of-n.json``. ``workers > 1`` runs the estimators in that many
    processes (images in order); this process writes the store. Otherwise, with ``overlap``, a reader thread
    decodes and aligns the next photos while this one runs the estimators (:mod:`.stream`)."""
    from tqdm import tqdm

    out = Path(out_dir)
    spec = sharding.parse(shard)
    files = list_inputs(in_dir)
    ids = record_ids(files)
    files = sharding.select(files, spec, key=lambda f: ids[f])
    store = EncodingStore.create(out, pipeline.dims(), pipeline.encodings,
                                 {"source": "difareli-preprocess", "size": pipeline.size, "gamma": "none"},
                                 durable=durable)
    if previews:
        (out / PREVIEWS).mkdir(parents=True, exist_ok=True)
    summary = RunSummary()
    busy = 0.0
    t_start = time.perf_counter()
    todo = []
    for f in files:
        if store.has(ids[f]) and not overwrite:
            summary.skipped += 1
            summary.entries.append({"file": str(f), "id": ids[f], "status": "skipped", "reason": "record exists"})
        else:
            todo.append(f)
    preview_dir = out / PREVIEWS if previews else None
    if workers > 1 and len(todo) > 1:
        results = compute_in_workers(pipeline, todo, preview_dir, ids, workers)
    elif overlap and len(todo) > 1:
        results = compute_streamed(pipeline, todo, preview_dir, ids, write=lambda f, res: store.write(
            ids[f], res["arrays"], res["meta"], overwrite=overwrite))
    else:
        results = (compute_one(pipeline, f, preview_dir and preview_dir / f"{ids[f]}.png") for f in todo)
    t_work = time.perf_counter()
    bar = tqdm(zip(todo, results), total=len(todo), desc="preprocess", unit="img", disable=not progress)
    for f, res in bar:
        rid = ids[f]
        entry: dict[str, Any] = {"file": str(f), "id": rid, **res["entry"]}
        if entry["status"] == "ok":
            announce(f, entry, res["arrays"], tqdm.write)
            try:
                if "write_error" in res:
                    raise res["write_error"]
                if not res.get("written"):
                    store.write(rid, res["arrays"], res["meta"], overwrite=overwrite)
                for k, v in res["meta"]["seconds"].items():
                    summary.stages[k] = summary.stages.get(k, 0.0) + v
                summary.written += 1
                busy += res["seconds"]
            except Exception as e:  # noqa: BLE001 - a bad record must not stop the other images
                entry.update(status="failed", reason=f"internal error: {type(e).__name__}: {e}")
        if entry["status"] == "failed":
            summary.failed += 1
        entry["seconds"] = round(res["seconds"], 3)
        summary.entries.append(entry)
        bar.set_postfix(ok=summary.written, failed=summary.failed)
    if workers > 1 and len(todo) > 1:
        busy = time.perf_counter() - t_work  # images/s of the whole pool: wall time, not the sum over workers
    bar.close()
    summary.seconds = busy
    report = {"in_dir": str(in_dir), "out_dir": str(out), "encodings": list(pipeline.encodings),
              "size": pipeline.size, "written": summary.written, "skipped": summary.skipped,
              "failed": summary.failed, "images_per_second": round(summary.images_per_second, 3),
              "wall_seconds": round(time.perf_counter() - t_start, 3),
              "stage_ms_per_image": summary.stage_ms(), "images": summary.entries}
    name = REPORT if spec is None else REPORT.replace(".json", f".{spec.suffix}.json")
    write_json_atomic(out / name, report, indent=1)
    return summary
