"""The preprocessing pipeline: photo -> aligned crop -> only the estimators the requested encodings need ->
one store record per image, a preview per image and a report of every input.

Estimators are plain objects with ``provides``/``requires`` (names of encodings or of intermediate products
such as ``landmarks`` or ``gbuffer``) and ``__call__(ctx, needed) -> dict``; :meth:`Pipeline.plan` runs an
estimator only if something requested depends on one of its outputs.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from difareli.encodings import ENCODINGS
from difareli.store import EncodingStore

from .loading import BadInput, list_inputs, load_image, record_ids

REPORT = "preprocess_report.json"
#: Estimator roles of a config's ``estimators`` block, in the order they are instantiated.
ROLES = ("geometry", "masks", "light", "identity", "shadow")
PREVIEWS = "previews"


class Pipeline:
    """An aligner plus estimators; ``encodings`` (default: every encoding of the schema a photo can give, i.e.
    all but the synthetic ground truth) decide which estimators run."""

    def __init__(self, aligner, estimators: Sequence[Any], encodings: Iterable[str] | None = None,
                 min_side: int = 64, max_side: int = 8192):
        self.aligner = aligner
        self.estimators = [e for e in estimators if e is not None]
        estimable = tuple(n for n, e in ENCODINGS.items() if not e.oracle)
        self.encodings = estimable if encodings is None else tuple(dict.fromkeys(encodings))
        unknown = [e for e in self.encodings if e not in ENCODINGS]
        if unknown:
            raise ValueError(f"unknown encodings {unknown}; the schema has {list(ENCODINGS)}")
        self.min_side, self.max_side = min_side, max_side
        self.steps, self.needed = self.plan(self.encodings)

    @classmethod
    def from_config(cls, estimators: Mapping[str, Any], encodings: Iterable[str] | None = None,
                    **kwargs: Any) -> "Pipeline":
        """Instantiate the aligner and the estimators of an ``estimators`` config block (``conf/preprocess/``:
        ``align`` plus one entry per role) into a Pipeline for ``encodings``."""
        from hydra.utils import instantiate

        roles = [instantiate(estimators[r]) for r in ROLES if estimators.get(r)]
        return cls(instantiate(estimators["align"]), roles, encodings, **kwargs)

    @property
    def size(self) -> int:
        return self.aligner.size

    def plan(self, encodings: Sequence[str]) -> tuple[list[Any], set[str]]:
        """Estimators to run (in dependency order) and every product needed, for ``encodings``."""
        producer = {}
        for est in self.estimators:
            for name in est.provides:
                producer.setdefault(name, est)
        needed, todo, chosen = set(), [n for n in encodings if n != "image"], []
        while todo:
            name = todo.pop()
            if name in needed:
                continue
            needed.add(name)
            if name not in producer:
                raise ValueError(f"no configured estimator provides {name!r} (configured: "
                                 f"{[type(e).__name__ for e in self.estimators]})")
            est = producer[name]
            if est not in chosen:
                chosen.append(est)
            todo.extend(r for r in est.requires if r != "image")
        steps, done = [], {"image"}
        while len(steps) < len(chosen):  # topological order by requirements
            ready = [e for e in chosen if e not in steps and set(e.requires) <= done]
            if not ready:
                raise ValueError("estimator requirements form a cycle or are missing: "
                                 f"{[(type(e).__name__, e.requires) for e in chosen if e not in steps]}")
            steps.append(ready[0])
            done |= set(ready[0].provides)
        return steps, needed

    def dims(self) -> dict[str, int]:
        from .geometry import SHAPE_DIM
        from .identity import IDENTITY_DIM

        # S belongs to whichever estimator writes ``shape`` (FaceMesh points: 1404, BFM fit: 53).
        producer = next((e for e in self.estimators if "shape" in e.provides), None)  # as in ``plan``
        shape_dim = getattr(producer, "shape_dim", SHAPE_DIM)
        return {"H": self.size, "W": self.size, "S": shape_dim, "D": IDENTITY_DIM}

    def process(self, rgb: np.ndarray) -> tuple[dict[str, np.ndarray], dict, dict]:
        """Encodings of one decoded photo, its meta, and the full context (for previews)."""
        t0 = time.perf_counter()
        aligned = self.aligner(rgb)
        ctx: dict[str, Any] = {"image": aligned["image"], "notes": list(aligned["notes"])}
        meta = {"faces": aligned["faces"], "box": aligned["box"], "quad": np.round(aligned["quad"], 2).tolist()}
        timings = {"align": time.perf_counter() - t0}
        for est in self.steps:
            t0 = time.perf_counter()
            out = est(ctx, self.needed)
            timings[type(est).__name__] = time.perf_counter() - t0
            ctx["notes"] += out.pop("notes", [])
            ctx.update(out)
        meta["seconds"] = {k: round(v, 4) for k, v in timings.items()}
        for key in ("reprojection_px", "bfm_fit", "light_fit", "shadow_info"):
            if key in ctx:
                meta[key] = ctx[key]
        arrays = {name: ctx[name] for name in self.encodings}
        return arrays, meta, ctx


@dataclass
class RunSummary:
    """What one run did; ``entries`` is the report's per-file list."""

    written: int = 0
    skipped: int = 0
    failed: int = 0
    seconds: float = 0.0
    entries: list[dict] = field(default_factory=list)

    @property
    def images_per_second(self) -> float:
        return self.written / self.seconds if self.seconds > 0 else 0.0


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(obj, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)) + "\n")
    os.replace(tmp, path)


def run(pipeline: Pipeline, in_dir: str, out_dir: str, *, overwrite: bool = False, previews: bool = True,
        durable: bool = False, progress: bool = True, shard: str | None = None) -> RunSummary:
    """Process every file of ``in_dir`` (or the single file) into the store at ``out_dir``; never raises
    for a bad image: each gets a report entry and nothing is written for it. ``shard="i/n"`` processes only
    the records of that shard (``difareli.shard``; shards may run concurrently into one store) and writes
    its report as ``preprocess_report.shard-i-of-n.json``."""
    from tqdm import tqdm

    from difareli import shard as sharding

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
    bar = tqdm(files, desc="preprocess", unit="img", disable=not progress)
    for f in bar:
        rid = ids[f]
        entry: dict[str, Any] = {"file": str(f), "id": rid}
        if store.has(rid) and not overwrite:
            entry["status"] = "skipped"
            entry["reason"] = "record exists"
            summary.skipped += 1
            summary.entries.append(entry)
            continue
        t0 = time.perf_counter()
        try:
            rgb, notes = load_image(f, pipeline.min_side, pipeline.max_side)
            arrays, meta, ctx = pipeline.process(rgb)
            notes += ctx["notes"]
            meta.update(source_file=f.name, input_size=list(rgb.shape[:2]), notes=notes, split="predict")
            store.write(rid, arrays, meta, overwrite=overwrite)
            if previews:
                from .preview import save_preview

                save_preview(out / PREVIEWS / f"{rid}.png", ctx)
            entry.update(status="ok", notes=notes, faces=meta["faces"])
            for key in ("reprojection_px", "bfm_fit", "light_fit"):
                if key in meta:
                    entry[key] = meta[key]
            summary.written += 1
        except BadInput as e:
            entry.update(status="failed", reason=str(e))
        except Exception as e:  # noqa: BLE001 - an estimator bug must not stop the other images
            entry.update(status="failed", reason=f"internal error: {type(e).__name__}: {e}")
        dt = time.perf_counter() - t0
        entry["seconds"] = round(dt, 3)
        if entry["status"] == "failed":
            summary.failed += 1
        else:
            busy += dt
        summary.entries.append(entry)
        bar.set_postfix(ok=summary.written, failed=summary.failed)
    bar.close()
    summary.seconds = busy
    report = {"in_dir": str(in_dir), "out_dir": str(out), "encodings": list(pipeline.encodings),
              "size": pipeline.size, "written": summary.written, "skipped": summary.skipped,
              "failed": summary.failed, "images_per_second": round(summary.images_per_second, 3),
              "wall_seconds": round(time.perf_counter() - t_start, 3), "images": summary.entries}
    _write_json(out / (REPORT if spec is None else REPORT.replace(".json", f".{spec.suffix}.json")), report)
    return summary
