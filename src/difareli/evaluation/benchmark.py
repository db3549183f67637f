"""Benchmark a relighting method on the protocols of SPEC 11 (the paper's Tables I/II/IV): a SynthFaces store, or a
Multi-PIE store made by ``difareli-multipie`` from a user's copy (the same ``protocols.json``).

For each pair (:mod:`difareli.evaluation.pairs`): relight ``source`` under the light fitted to ``light_source``
(protocol (i) ``same_subject``: the same person under the target light; (ii) ``different_subject``: another person
under that very light) as a user would get it (:class:`~difareli.lighting.light_fit.LightFit`), with the shadow
strength c a user has (``data.target_shadow.target_shadow_of``), and score it against ``target`` on its ``score_mask``
(:class:`~difareli.evaluation.scoring.Scoring`) through the torchmetrics ``Metric`` s of
:func:`difareli.evaluation.metrics.relight_metrics`.
``oracle_light`` takes the exact light and c instead (``light_gt`` / ``shadow_gt`` where the store's ``light`` /
``shadow`` are estimated), ``oracle_shadow`` the exact c alone; a store without exact lights (``"exact_lights":
false`` in ``protocols.json``: Multi-PIE) gets no light-estimation errors and no oracle. ``summary.md`` and
``provenance.json`` state which inputs were used, the metric rule and the data set.

Beyond DSSIM / MSE / LPIPS (:mod:`difareli.evaluation.extras`), each row carries the identity cosines of
the relit face (vs the input, vs the ground truth), the lighting error of the relit image against the target light
and the shadow adherence to the target's cast shadow, where the store and the installed extras allow them (an absent
column is one line in ``summary.md`` saying why), and the strata ``difareli-table strata=`` groups by.

A run is a :class:`BenchmarkJob` (checked at the command's door); outputs in its run dir:
``relit/<protocol>/<pair id>.png``, ``metrics_per_image.csv`` (tables.py schema), ``summary.{md,csv,tex}``,
``light_estimation.csv`` (:mod:`difareli.evaluation.result`) and ``comparison_<protocol>.png`` (input | light source |
relit | ground truth for the first pairs). Every file is written atomically (a full disk is one line naming it,
nothing half-written; rows already scored are kept and a rerun resumes from them).
"""

from __future__ import annotations

import json
import sys
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from tqdm.auto import tqdm

from difareli import errors
from difareli.data import provenance, shard as sharding
from difareli.evaluation import metrics, tables
from difareli.evaluation.extras import PairExtras
from difareli.utils import viz
from difareli.evaluation.baselines import Method
from difareli.evaluation.batched import BatchedRelights, Made
from difareli.lighting.light_fit import LightFit
from difareli.evaluation.result import BenchmarkResult, write_outputs
from difareli.evaluation.scoring import DEFAULT_MASK, Scoring, score
from difareli.utils.fileio import RESUME, append_csv_row, folder_lock, on_full_disk, read_json_mapping
from difareli.data.store import CorruptRecordError, EncodingStore
from difareli.data.protocols import PROTOCOLS
from difareli.evaluation.pairs import Lights, Pair, StoredFace, load_pairs, protocols_doc

#: Rows scored so far, appended one by one: a killed run resumes from them (removed when the run completes).
PARTIAL_CSV = ".metrics_per_image.partial.csv"
#: What scored a run's rows (difareli.data.provenance): a resumed run must match it.
SETTINGS = "benchmark_settings.json"


def _scored_so_far(out_dir: Path, method: str, rule: str) -> dict[tuple[str, str], tables.Record]:
    """Rows of an interrupted run of ``method`` under ``rule`` in ``out_dir`` by (protocol, pair id); a cut last
    row is dropped."""
    path = out_dir / PARTIAL_CSV
    if not path.is_file():
        return {}
    try:
        rows, _ = tables.read_records_checked(path, drop_bad_rows=True)
    except tables.TableError:  # an unreadable partial CSV: start over (other errors are not the file's)
        return {}
    return {(r.protocol, r.record_id): r for r in rows if r.method == method and r.rule == rule}


def _read_png(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    return np.asarray(iio.imread(path))[..., :3]


@dataclass(frozen=True)
class BenchmarkJob:
    """One benchmark run, its values checked at the command's door: ``method`` on the pairs of ``protocols`` in
    ``store`` (at most ``limit`` per protocol, evenly spaced; with ``shard="i/n"`` that shard's alone, by pair id:
    the n shards' rows are the unsharded run's, which ``difareli-table`` merges), under the lights ``estimator``
    fits (exact ones with ``oracle_light``; the exact c alone with ``oracle_shadow``), scored as ``scoring`` says,
    written into ``out_dir`` with the first ``grid_pairs`` pairs of each protocol in its comparison grid."""

    store: EncodingStore
    method: Method
    protocols: tuple[str, ...]
    out_dir: Path
    scoring: Scoring
    limit: int | None = None
    oracle_light: bool = False
    oracle_shadow: bool = False
    estimator: LightFit | None = None
    grid_pairs: int = 4
    save_images: bool = True
    progress: bool = True
    shard: sharding.Shard | str | None = None

    @classmethod
    def of(cls, store: EncodingStore, method: Method, protocols: Sequence[str], out_dir: str | Path, *,
           scoring: Scoring | None = None, **values: Any) -> "BenchmarkJob":
        """The job of these values, by keyword (``scoring`` None: :class:`Scoring`'s defaults for the store)."""
        return cls(store, method, tuple(protocols), Path(out_dir), scoring or Scoring.of(store), **values)

    def run(self) -> BenchmarkResult:
        """Relight and score every pair (module doc) and write the run's outputs. ``out_dir`` is locked for the run,
        and :data:`SETTINGS` records what scores its rows (:meth:`settings`): a resumed run with other settings is
        refused, naming what differs, instead of keeping another checkpoint's rows."""
        if hasattr(self.method, "check_store"):  # a model that cannot read the store: one line, not a failed row each
            self.method.check_store(self.store)
        out = self.out_dir
        with folder_lock(out, "benchmark"), on_full_disk(out, scratch=[out], fix=RESUME):
            settings = self.settings()
            recorded = read_json_mapping(out / SETTINGS)  # {} if none; an unreadable one: provenance.ensure's
            if self.scoring.score_mask == DEFAULT_MASK and recorded and "score_mask" not in recorded:
                settings.pop("score_mask")  # rows of a run from before the option: scored on face_mask, resumable
            provenance.ensure(out, settings, "benchmark rows", name=SETTINGS,
                              has_results=(out / PARTIAL_CSV).is_file() or (out / tables.PER_IMAGE_CSV).is_file())
            return _run(*_start(self))

    def finished(self) -> BenchmarkResult | None:
        """The completed run in ``out_dir`` when it was made with exactly these settings (its scored rows and what it
        states about its inputs), else None: what a whole suite rerun reuses instead of relighting again. A killed
        run (rows still partial) is not finished: it is resumed."""
        out_dir = self.out_dir
        if not (out_dir / tables.PER_IMAGE_CSV).is_file() or (out_dir / PARTIAL_CSV).is_file():
            return None
        if provenance.differences(read_json_mapping(out_dir / SETTINGS), provenance.plain(self.settings())):
            return None
        try:
            stated = json.loads((out_dir / provenance.PROVENANCE).read_text())
        except (OSError, ValueError):
            return None
        return BenchmarkResult(records=tables.read_records(out_dir / tables.PER_IMAGE_CSV), provenance=stated)

    def settings(self) -> dict[str, Any]:
        """What decides the run's rows (compared when a run resumes into the same folder). ``target_sun`` counts
        only where it changes a relight: fitted lights and a method that reads a shadow map."""
        relighter = getattr(self.method, "relighter", None)
        model = getattr(relighter, "model", None)
        marched = {"target_sun": self.scoring.target_sun} if self.marches else {}
        return {"method": self.method.name, "model": provenance.model_identity(model) if model is not None else None,
                "sampler": relighter.spec.to_config() if getattr(relighter, "spec", None) is not None else None,
                "precision": relighter.runtime.precision if relighter is not None else None,
                "store": provenance.store_identity(self.store),
                "versions": dict(getattr(self.store, "versions", {}) or {}),
                "protocols": list(self.protocols), "limit": self.limit, "oracle_light": bool(self.oracle_light),
                "oracle_shadow": bool(self.oracle_shadow), "rule": self.scoring.rule,
                "score_mask": self.scoring.score_mask, "shard": self.shard, **marched}

    @property
    def marches(self) -> bool:
        """Whether the relights depend on where a target shadow map is marched: fitted lights, and a method that
        reads the map."""
        relighter = getattr(self.method, "relighter", None)
        return (not self.oracle_light and relighter is not None
                and "shadow_map" in getattr(relighter, "model_inputs", ()))


def run_benchmark(store: EncodingStore, method: Method, protocols: Sequence[str], out_dir: str | Path,
                  **values: Any) -> BenchmarkResult:
    """:meth:`BenchmarkJob.run` of these values (:meth:`BenchmarkJob.of`)."""
    return BenchmarkJob.of(store, method, protocols, out_dir, **values).run()


@dataclass
class _Run:
    """What every pair of one run shares: its ``job``, the store's ``protocols.json`` (``doc``, read once), the
    pairs' ``lights`` and ``extras``; ``columns``: the extra CSV columns; ``exact``: the store holds exact lights;
    ``source_light``: the method's own source-light fit (its error is measured too)."""

    job: BenchmarkJob
    doc: dict
    lights: Lights
    extras: PairExtras
    columns: list[str]
    exact: bool
    source_light: Callable[[StoredFace], np.ndarray] | None


def _run(run: _Run, result: BenchmarkResult) -> BenchmarkResult:
    """Every pair relit and scored (or resumed from the partial CSV), then the run's outputs written."""
    job = run.job
    store, method, out_dir = job.store, job.method, job.out_dir
    rule, score_mask = job.scoring.rule, job.scoring.score_mask
    done = _scored_so_far(out_dir, method.name, rule)
    selected = {proto: list(sharding.select(pairs, job.shard, key=lambda p: p.id))
                for proto, pairs in load_pairs(store, job.protocols, job.limit, run.doc).items()}
    batched = BatchedRelights(store, method, run.lights, job.oracle_shadow,
                              [(PROTOCOLS[proto], pair) for proto, pairs in selected.items() for pair in pairs
                               if (PROTOCOLS[proto], pair.id) not in done])
    for proto, pairs in selected.items():
        short = PROTOCOLS[proto]
        grid_rows: list[list[np.ndarray]] = []
        scorer = metrics.relight_metrics(rule)  # this run's scores of the protocol (rows resumed are not in it)
        for pair in tqdm(pairs, desc=f"{method.name} {proto}", disable=not job.progress):
            light, shadow = run.lights.for_pair(pair, oracle_shadow=job.oracle_shadow)
            result.provenance.setdefault("target c", run.lights.shadow_note)
            made = batched.get(short, pair)  # None for a pair resumed or relit on its own
            # Each record read once: the source as its batch read it, or here (with the ground truth).
            source = made.source if made is not None else StoredFace(store, pair.source)
            target = StoredFace(store, pair.target)
            if run.exact:  # the fitted lights' errors
                result.light_errors += [{"protocol": short, **e}
                                        for e in run.lights.errors(pair, light, run.source_light, source)]
            png = out_dir / "relit" / proto / f"{pair.id}.png"
            want_grid = len(grid_rows) < job.grid_pairs
            prev = done.get((short, pair.id))
            if prev is not None and (not want_grid or prev.status != "ok" or png.is_file()):
                # scored before the run was killed: not redone
                rec, relit = prev, _read_png(png) if want_grid and prev.status == "ok" else None
            else:
                rec, relit = _relight_and_score(run, pair, source, target, light, shadow, scorer, made)
                _keep(run, rec, relit, png)
            result.records.append(rec)
            if want_grid and relit is not None:  # input | light source | relit | ground truth
                grid_rows.append([source.image, StoredFace(store, pair.light_source).image, relit, target.image])
        result.metric_stats[short] = {k: m.stat() for k, m in scorer.items()}
        if grid_rows:
            result.paths[f"comparison_{proto}"] = viz.save_png(viz.grid(grid_rows), out_dir / f"comparison_{proto}.png")
    result.paths.update(write_outputs(result, out_dir, caption=f"{method.name} on {Path(store.root).name}"
                                      + ("" if score_mask == DEFAULT_MASK else f", scored on {score_mask}")))
    (out_dir / PARTIAL_CSV).unlink(missing_ok=True)
    return result


def _start(job: BenchmarkJob) -> tuple[_Run, BenchmarkResult]:
    """The run's shared inputs and its result so far: what it states about its inputs, no rows yet."""
    store, method, scoring = job.store, job.method, job.scoring
    doc = protocols_doc(store)
    exact = bool(doc.get("exact_lights", True))
    if job.oracle_light and not exact:
        raise errors.UserError(f"oracle_light=true but {store.root} holds no exact lights (a "
                               f"{doc.get('dataset', 'photo')} store); drop oracle_light")
    estimator = job.estimator or LightFit()
    extras = PairExtras(store, scoring.score_mask, fit=estimator)
    result = BenchmarkResult(records=[], provenance={
        "target light": "exact (oracle_light)" if job.oracle_light else "fitted to the light-source image (LightFit)",
        "target maps": getattr(method, "target_maps", "none (the method reads no light-dependent map)"),
        "data set": str(doc.get("dataset", "synthfaces")), "metrics rule": scoring.rule,
        "score mask": scoring.score_mask})
    result.provenance.update({**extras.provenance(), "store": f"{store.root} ({provenance.store_identity(store)})"})
    result.notes = list(extras.notes)
    # Methods that fit their source light (the Lambertian baseline) are scored on it too, through their own door.
    fits = method.needs_light_fit and getattr(method, "estimator", None) is not None
    lights = Lights(store, None if job.oracle_light else estimator,
                    sun_from_shadows=job.marches and scoring.target_sun == "shadows")
    if job.marches:
        result.provenance["target sun"] = ("found from the light-source image's cast shadows (render.sun_fit)"
                                           if scoring.target_sun == "shadows" else "the fitted light's radiance peak")
    run = _Run(job, doc, lights, extras, [*extras.metrics(), *extras.strata()], exact,
               method.source_light if fits else None)
    return run, result


def _relight_and_score(run: _Run, pair: Pair, source: StoredFace, target: StoredFace, light: np.ndarray,
                       shadow: float | None, scorer, made: Made | None = None
                       ) -> tuple[tables.Record, np.ndarray | None]:
    """One pair relit by the method and scored: its row and relit image, or (a bad pair) its failed row and None.
    Its source is read whole and checked once: here (the method takes its encodings from it), or, for a pair
    ``made`` in a batch, by :class:`~difareli.evaluation.batched.BatchedRelights`; the target light and shadow are
    checked by the method's relight (a model's ``Targets``)."""
    job = run.job
    name, short = job.method.name, PROTOCOLS[pair.protocol]
    rule, mask = job.scoring.rule, job.scoring.score_mask
    gt = target.read(["image", mask])
    start = time.perf_counter()
    # Only a bad pair is a failed row, reported as failed, never a score: a non-finite input or result, or
    # a record whose file is corrupt. Other user errors (a missing record or encoding, an image too small
    # to score, a method's wrong output) hold for every pair: they stop the run with their message.
    try:
        if made is None:
            errors.check_record(source.read(), pair.source, job.store.root)
            relit = job.method.relight(source, light, shadow, target=target, target_sun=run.lights.sun(pair))
            seconds = time.perf_counter() - start
        else:
            relit, seconds = made.relit, made.seconds
        relit = errors.check_output(relit, f"{name} relight of pair {pair.id}")
        if relit.shape != gt["image"].shape or relit.dtype != np.uint8:
            raise errors.UserError(f"{name} returned {relit.dtype} {relit.shape}; expected uint8 {gt['image'].shape}")
        s = score(relit, gt["image"], gt[mask], rule, scorer)
        errors.check_finite(list(s.values()), f"scores of pair {pair.id} (is its {mask} empty?)")
    except (errors.NonFiniteError, CorruptRecordError) as e:
        print(f"FAILED {pair.protocol} {pair.id}: {e}", file=sys.stderr)
        ex, info = run.extras.empty(target)
        return tables.Record(name, short, pair.id, math.nan, math.nan, math.nan, time.perf_counter() - start,
                             status="failed", rule=rule, extra=ex, info=info), None
    ex, info = run.extras(relit, source, target, light)
    return tables.Record(name, short, pair.id, s["dssim"], s["mse"], s["lpips"], seconds, rule=rule,
                         extra=ex, info=info), relit


def _keep(run: _Run, rec: tables.Record, relit: np.ndarray | None, png: Path) -> None:
    """A newly scored pair's relit PNG (if the run saves images), then its row with the run's extra columns in the
    partial CSV (whole or not at all: a full disk leaves the rows before it intact)."""
    if relit is not None and run.job.save_images:
        viz.save_png(relit, png)
    header = tables.header(run.columns)  # the row after the image: a resumed run finds both
    append_csv_row(run.job.out_dir / PARTIAL_CSV, header, dict(zip(header, tables.record_row(rec, extra=run.columns))))
