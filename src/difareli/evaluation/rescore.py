"""``difareli-benchmark rescore=<run dir>`` (:class:`Rescore`): a finished run's saved relit PNGs scored again
(another metric rule or mask, and the extra columns of :mod:`difareli.evaluation.extras`) without relighting, against
the run's own store only and from a per-image CSV that holds each of the run's pairs exactly once, each row of the
method and rule the run recorded."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from difareli import errors
from difareli.data import provenance
from difareli.data import shard as sharding
from difareli.data.store import EncodingStore
from difareli.evaluation import metrics, tables
from difareli.data.protocols import PROTOCOLS
from difareli.evaluation.benchmark import SETTINGS
from difareli.evaluation.result import BenchmarkResult, write_outputs
from difareli.evaluation.scoring import Scoring, score
from difareli.evaluation.pairs import Lights, StoredFace, load_pairs, protocols_doc
from difareli.evaluation.extras import PairExtras
from difareli.lighting.light_fit import LightFit
from difareli.utils.fileio import on_full_disk, write_json_atomic


@dataclass(frozen=True)
class Rescore:
    """The relit PNGs a finished run in ``run_dir`` saved (``relit/<protocol>/<pair id>.png``) scored again as
    ``scoring`` says (the benchmark's :class:`~.scoring.Scoring`, checked at the door), into ``out_dir``: the same
    images, another metric rule or mask (seconds and failed rows are kept from the run). The lighting error refits
    the target light with ``estimator`` (default LightFit)."""

    store: EncodingStore
    run_dir: Path
    out_dir: Path
    scoring: Scoring
    estimator: LightFit | None = None

    def run(self) -> BenchmarkResult:
        """The rescored result, its files written. The store must be the run's (its recorded identity), and the
        run's CSV must hold each of its pairs exactly once; each file of the run is read once."""
        store, run_dir, out_dir, estimator = self.store, self.run_dir, self.out_dir, self.estimator
        rule, score_mask = self.scoring.rule, self.scoring.score_mask
        # each readable or absent
        settings, stated = (_run_json(run_dir, name) for name in (SETTINGS, "provenance.json"))
        _check_same_store(store, run_dir, settings, stated)
        rows = tables.read_records(run_dir / tables.PER_IMAGE_CSV)
        doc = protocols_doc(store)  # read once, for both of its uses
        _check_rows(store, run_dir, rows, settings, doc)
        pairs = {(PROTOCOLS[p.protocol], p.id): p for v in load_pairs(store, list(PROTOCOLS), doc=doc).values()
                 for p in v}
        result = BenchmarkResult(records=[], provenance={**stated, "metrics rule": rule, "score mask": score_mask,
                                                         "rescored from": str(run_dir)})
        extras = PairExtras(store, score_mask, fit=estimator)
        result.provenance.update(extras.provenance())
        result.notes = list(extras.notes)
        oracle = bool(settings.get("oracle_light"))
        lights = Lights(store, None if oracle else (estimator or LightFit()))
        scorers = {short: metrics.relight_metrics(rule) for short in PROTOCOLS.values()}
        for r in rows:
            pair = pairs.get((r.protocol, r.record_id))
            source, target = ((StoredFace(store, pair.source), StoredFace(store, pair.target)) if pair
                              else (None, None))
            if r.status != "ok":
                ex, info = extras.empty(target) if pair else ({}, {})
                result.records.append(dataclasses.replace(r, rule=rule, extra=ex, info=info))
                continue
            png = run_dir / "relit" / (pair.protocol if pair else "?") / f"{r.record_id}.png"
            if pair is None or not png.is_file():
                raise errors.UserError(f"rescore={run_dir}: no relit image {png} for {r.protocol} pair "
                                       f"{r.record_id} (was the run made with save_images=true on this store?); "
                                       "rerun the benchmark")
            gt = target.read(["image", score_mask])
            relit = _relit_png(png, run_dir, np.shape(gt["image"])[:2])
            s = score(relit, gt["image"], gt[score_mask], rule, scorers[r.protocol])
            ex, info = extras(relit, source, target, lights.get(pair.target if oracle else pair.light_source))
            result.records.append(dataclasses.replace(r, dssim=s["dssim"], mse=s["mse"], lpips=s["lpips"],
                                                      rule=rule, extra=ex, info=info))
        result.metric_stats = {p: {k: m.stat() for k, m in sc.items()} for p, sc in scorers.items()}
        with on_full_disk(out_dir, scratch=[out_dir]):
            if settings:  # the rescored folder records its store too: a rescore of it is checked the same way
                write_json_atomic(out_dir / SETTINGS, {**settings, "rule": rule, "score_mask": score_mask})
            result.paths.update(write_outputs(result, out_dir, caption=f"{run_dir.name} rescored ({rule})"))
        return result


def _run_json(run_dir: Path, name: str) -> dict:
    """``run_dir``'s JSON file ``name`` as an object ({} where the run wrote none); a run dir that is none, or a file
    that is no JSON object, is one line (it was a JSONDecodeError or RecursionError traceback, or "records no store
    identity" for a folder that does not exist)."""
    fix = "give the out_dir of a finished difareli-benchmark run (save_images=true)"
    if not run_dir.is_dir():
        raise errors.UserError(f"rescore={run_dir} {'does not exist' if not run_dir.exists() else 'is a file'}; {fix}")
    if not (run_dir / tables.PER_IMAGE_CSV).is_file():
        what = "is an encodings store" if (run_dir / "store.json").is_file() else "holds no per-image CSV"
        raise errors.UserError(f"rescore={run_dir} {what}, not a benchmark run dir; {fix}")
    path = run_dir / name
    if not path.is_file():
        return {}
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as e:
        doc = e
    if not isinstance(doc, dict):
        why = f"{type(doc).__name__}" if isinstance(doc, BaseException) else f"a JSON {type(doc).__name__}"
        raise errors.UserError(f"rescore={run_dir}: {name} is not the JSON object the benchmark writes ({why}): "
                               "corrupt; restore it or rerun the benchmark")
    return doc


def _relit_png(png: Path, run_dir: Path, size: tuple[int, ...]) -> np.ndarray:
    """A saved relit image as the benchmark wrote it (8-bit RGB of the store's size), or one line naming the file:
    a replaced file was a traceback (not a PNG) or a metrics error naming no file (another size)."""
    fix = "restore the run's relit images or rerun the benchmark"
    import imageio.v3 as iio

    try:
        relit = np.asarray(iio.imread(png))  # as the benchmark's _read_png, less its [..., :3] (said below instead)
    except Exception as e:  # noqa: BLE001 - imageio raises plugin-specific errors
        raise errors.UserError(f"rescore={run_dir}: {png} is not a readable image ({type(e).__name__}); "
                               f"{fix}") from None
    if relit.ndim != 3 or relit.shape[:2] != tuple(size) or relit.shape[2] not in (3, 4) or relit.dtype != np.uint8:
        raise errors.UserError(f"rescore={run_dir}: {png} is {'x'.join(map(str, relit.shape))} {relit.dtype}, the "
                               f"benchmark writes {size[0]}x{size[1]}x3 uint8 (the store's size); {fix}")
    return relit[..., :3]


def _check_same_store(store: EncodingStore, run_dir: Path, settings: dict, stated: dict) -> None:
    """A rescore reads the ground truths of the store the run was scored on, or nothing: the same record ids in
    another store would score the saved images against other ground truths (``settings`` and ``stated``: the run's
    :data:`~.benchmark.SETTINGS` and provenance.json)."""
    have, now = settings.get("store"), provenance.store_identity(store)
    if have is None:
        raise errors.UserError(f"rescore={run_dir}: the run records no store identity ({SETTINGS} missing or "
                               "without 'store'), so nothing says its images belong to this store; rerun the benchmark")
    if have != now:
        where = stated.get("store")
        raise errors.UserError(f"rescore={run_dir}: the run was scored on store {where or have}, store={store.root} "
                               f"is another one ({now}); rescore against the run's own store")


def _check_recorded(run_dir: Path, rows: Sequence[tables.Record], settings: dict) -> None:
    """Every row is the run's: its method and metric rule are the ones the run recorded (an edited row would be
    scored from another method's image under its own name)."""
    want = {"method": settings.get("method"), "rule": settings.get("rule")}
    for line, r in enumerate(rows, start=2):  # line 1 is the header; every row was read (bad rows are refused)
        for key, value in want.items():
            if value is not None and getattr(r, key) != value:
                raise errors.UserError(f"rescore={run_dir}: {tables.PER_IMAGE_CSV} line {line} ({r.protocol} "
                                       f"{r.record_id}) has {key} {getattr(r, key)!r}, the run recorded {value!r} "
                                       f"({SETTINGS}); the CSV was edited: restore it or rerun the benchmark")


def _check_rows(store: EncodingStore, run_dir: Path, rows: Sequence[tables.Record], settings: dict,
                doc: dict) -> None:
    """Each pair of the run exactly once, as difareli-table requires (its pairs from ``doc``, the store's
    ``protocols.json``): duplicated or missing rows are refused; each row of the run's method and rule
    (:func:`_check_recorded`)."""
    _check_recorded(run_dir, rows, settings)
    seen: dict[tuple[str, str], int] = {}
    for r in rows:
        seen[(r.protocol, r.record_id)] = seen.get((r.protocol, r.record_id), 0) + 1
    dup = [k for k, n in seen.items() if n > 1]
    if dup:
        raise errors.UserError(f"rescore={run_dir}: {tables.PER_IMAGE_CSV} repeats {len(dup)} pair(s) (e.g. "
                               f"{dup[0][0]} {dup[0][1]} {seen[dup[0]]} times); each pair is scored once: remove the "
                               "repeated rows or rerun the benchmark")
    if "protocols" not in settings:
        return
    want = {(PROTOCOLS[p], q.id) for p, v in load_pairs(store, settings["protocols"], settings.get("limit"),
                                                        doc).items()
            for q in sharding.select(v, settings.get("shard"), key=lambda q: q.id)}
    missing, extra = sorted(want - set(seen)), sorted(set(seen) - want)
    if missing or extra:
        raise errors.UserError(f"rescore={run_dir}: {tables.PER_IMAGE_CSV} lacks {len(missing)} of the run's pairs "
                               f"(e.g. {missing[:2]}) and has {len(extra)} it did not score (e.g. {extra[:2]}); "
                               "rerun the benchmark to complete it")
