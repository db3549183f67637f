"""Benchmark a relighting method on the protocols of SPEC 11 (the paper's Tables I/II/IV): a SynthFaces store, or a
Multi-PIE store made by ``difareli-multipie`` from a user's copy (the same ``protocols.json``).

For each pair (:mod:`difareli.evaluation.pairs`): relight ``source`` under the light fitted to ``light_source``
(protocol (i) ``same_subject``: the same person under the target light; (ii) ``different_subject``: another person
under that very light) as a user would get it (:class:`~difareli.lighting.light_fit.LightFit`), with the shadow
strength c a user has (``targets.target_shadow_of``), and score it against ``target`` on its ``score_mask``
(:class:`Scoring`) through the torchmetrics ``Metric`` s of :func:`difareli.evaluation.metrics.relight_metrics`.
``oracle_light`` takes the exact light and c instead (``light_gt`` / ``shadow_gt`` where the store's ``light`` /
``shadow`` are estimated), ``oracle_shadow`` the exact c alone; a store without exact lights (``"exact_lights":
false`` in ``protocols.json``: Multi-PIE) gets no light-estimation errors and no oracle. ``summary.md`` and
``provenance.json`` state which inputs were used, the metric rule and the data set.

Beyond DSSIM / MSE / LPIPS (:mod:`difareli.evaluation.extras`), each row carries the identity cosines of
the relit face (vs the input, vs the ground truth), the lighting error of the relit image against the target light
and the shadow adherence to the target's cast shadow, where the store and the installed extras allow them (an absent
column is one line in ``summary.md`` saying why), and the strata ``difareli-table strata=`` groups by.

Outputs in the run dir: ``relit/<protocol>/<pair id>.png``, ``metrics_per_image.csv`` (tables.py schema),
``summary.{md,csv,tex}``, ``light_estimation.csv`` and ``comparison_<protocol>.png`` (input | light source |
relit | ground truth for the first pairs). Every file is written atomically (a full disk is one line naming it,
nothing half-written; rows already scored are kept and a rerun resumes from them).
"""

from __future__ import annotations

import json
import sys
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from difareli import errors
from difareli.data import encodings, provenance, shard as sharding
from difareli.evaluation import metrics, tables
from difareli.evaluation.extras import PairExtras
from difareli.utils import viz
from difareli.evaluation.baselines import Method
from difareli.evaluation.batched import BatchedRelights
from difareli.lighting.light_fit import LightFit
from difareli.utils.fileio import (RESUME, append_csv_row, atomic_path, folder_lock, on_full_disk,
                                   read_json_mapping, write_json_atomic, write_text_atomic)
from difareli.data.store import CorruptRecordError, EncodingStore
from difareli.data.protocols import PROTOCOLS
from difareli.evaluation.pairs import Lights, Pair, StoredFace, load_pairs, protocols_doc
from difareli.render.sun_fit import TARGET_SUNS

#: The light-estimation errors of a run (where the store holds exact lights).
LIGHT_CSV = "light_estimation.csv"
#: Rows scored so far, appended one by one: a killed run resumes from them (removed when the run completes).
PARTIAL_CSV = ".metrics_per_image.partial.csv"
#: What scored a run's rows (difareli.data.provenance): a resumed run must match it.
SETTINGS = "benchmark_settings.json"
#: The mask every pair is scored on unless ``score_mask`` names another one.
DEFAULT_MASK = "face_mask"


def check_score_mask(store: EncodingStore, key: str | None) -> str:
    """``key`` (None: :data:`DEFAULT_MASK`) if the store has it as a mask (a bool HxW encoding), else a UserError
    naming the masks it has."""
    key = DEFAULT_MASK if key is None else str(key)
    have = [n for n in store.encodings if n in encodings.ENCODINGS and encodings.get(n).dtype == "bool"
            and tuple(encodings.get(n).shape) == ("H", "W")]
    if key not in have:
        what = (f"has {key} but it is not a mask (a bool HxW encoding)" if store.available(key) else
                f"has no {key}")
        raise errors.UserError(f"score_mask={key}: store {store.root} {what}; give one of its masks: "
                               f"{', '.join(have)} (default score_mask={DEFAULT_MASK})")
    return key


@dataclass(frozen=True)
class Scoring:
    """How a run scores its pairs, checked once at the door (:meth:`of`): the metric ``rule`` (None: ``paper``), the
    ``score_mask`` (None: ``face_mask``) and ``target_sun``, where a fitted target light's cast-shadow maps are
    marched: ``shadows`` (toward the key sun found from the light-source image's cast shadows: ``render.sun_fit``)
    or ``peak`` (the fitted SH's radiance peak)."""

    rule: str
    score_mask: str
    target_sun: str = "shadows"

    @classmethod
    def of(cls, store: EncodingStore, rule: str | None = None, score_mask: str | None = None,
           target_sun: str = "shadows") -> "Scoring":
        """Each value checked, named as the benchmark's config spells it (None: the defaults)."""
        return cls(errors.check_choice(metrics.DEFAULT_RULE if rule is None else rule, "metrics.rule", metrics.RULES),
                   check_score_mask(store, score_mask), errors.check_choice(target_sun, "target_sun", TARGET_SUNS))


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


def score(pred: np.ndarray, target: np.ndarray, face_mask: np.ndarray, rule: str | None = None,
          scorer=None) -> dict[str, float]:
    """DSSIM / MSE / LPIPS of one uint8 image against the ground truth on the mask under ``rule``; through
    ``scorer`` (a :func:`metrics.relight_metrics` collection, which also accumulates the score) when given."""
    scorer = scorer if scorer is not None else metrics.relight_metrics(rule)
    mask = torch.from_numpy(np.array(face_mask, dtype=bool))[None]
    scorer.update(metrics.unit_tensor(pred), metrics.unit_tensor(target), mask)
    return {k: float(m.last[0]) for k, m in scorer.items()}


@dataclass
class BenchmarkResult:
    records: list[tables.Record]
    #: which inputs were estimated and which were oracle (stated in summary.md and provenance.json)
    provenance: dict[str, str] = field(default_factory=dict)
    light_errors: list[dict] = field(default_factory=list)
    paths: dict[str, Path] = field(default_factory=dict)
    #: protocol -> metric -> (mean, SE, n) of the pairs scored in this run, from the torchmetrics Metrics
    metric_stats: dict[str, dict[str, tuple[float, float, int]]] = field(default_factory=dict)
    #: lines under the table: why an extra metric column is absent
    notes: list[str] = field(default_factory=list)

    @property
    def table(self) -> tables.Table:
        table = tables.summarize(self.records)
        table.remarks = list(self.notes)
        return table

    def light_summary(self) -> str:
        """Markdown table of the light-estimation errors (mean ± SE per protocol and light)."""
        if not self.light_errors:
            return ""
        lines = ["| protocol | light | n | rel. irradiance error | after best gain |", "|---|---|---:|---:|---:|"]
        keys = list(dict.fromkeys((e["protocol"], e["light"]) for e in self.light_errors))
        for p, which in keys:
            rows = [e for e in self.light_errors if e["protocol"] == p and e["light"] == which]
            rel = tables.mean_se(r["rel_error"] for r in rows)
            free = tables.mean_se(r["rel_error_gain_free"] for r in rows)
            lines.append(f"| {tables.PROTOCOL_LABELS.get(p, p)} | {which} | {rel.n} | {_pm(rel)} | {_pm(free)} |")
        return "\n".join(lines) + "\n"


def _pm(s: tables.Stat) -> str:
    return f"{s.mean:.4f} ± {s.se:.4f}" if math.isfinite(s.se) else f"{s.mean:.4f}"


def run_benchmark(store: EncodingStore, method: Method, protocols: Sequence[str], out_dir: str | Path, *,
                  limit: int | None = None, oracle_light: bool = False, oracle_shadow: bool = False,
                  estimator: LightFit | None = None,
                  grid_pairs: int = 4, save_images: bool = True, progress: bool = True,
                  shard: str | None = None, scoring: Scoring | None = None) -> BenchmarkResult:
    """Relight and score every pair of ``protocols`` (module doc) and write the run's outputs into ``out_dir``, scored
    as ``scoring`` says (:class:`Scoring`, checked at the door; None: its defaults). ``shard="i/n"`` scores only that
    shard's pairs (by pair id, after ``limit``): the n shards' rows are
    the unsharded run's (``difareli-table`` merges them). ``out_dir`` is locked for the run, and :data:`SETTINGS`
    records what scores its rows (:func:`run_settings`): a resumed run with other settings is refused, naming what
    differs, instead of keeping another checkpoint's rows."""
    out_dir = Path(out_dir)
    scoring = scoring or Scoring.of(store)
    if hasattr(method, "check_store"):  # a model that cannot read the store: one line, not a failed row per pair
        method.check_store(store)
    with folder_lock(out_dir, "benchmark"), on_full_disk(out_dir, scratch=[out_dir], fix=RESUME):
        settings = run_settings(store, method, protocols, scoring, limit=limit, oracle_light=oracle_light,
                                oracle_shadow=oracle_shadow, shard=shard)
        recorded = read_json_mapping(out_dir / SETTINGS)  # {} if none; an unreadable one: provenance.ensure's
        if scoring.score_mask == DEFAULT_MASK and recorded and "score_mask" not in recorded:
            settings.pop("score_mask")  # rows of a run from before the option: scored on face_mask, resumable
        provenance.ensure(out_dir, settings, "benchmark rows", name=SETTINGS,
                          has_results=(out_dir / PARTIAL_CSV).is_file() or (out_dir / tables.PER_IMAGE_CSV).is_file())
        run, result = _start(store, method, out_dir, scoring, oracle_light=oracle_light, oracle_shadow=oracle_shadow,
                             estimator=estimator, save_images=save_images)
        return _run(run, result, protocols, limit=limit, shard=shard, grid_pairs=grid_pairs, progress=progress)


def finished_run(store: EncodingStore, method: Method, protocols: Sequence[str], out_dir: str | Path, *,
                 limit: int | None = None, oracle_light: bool = False, oracle_shadow: bool = False,
                 scoring: Scoring | None = None) -> BenchmarkResult | None:
    """The completed run in ``out_dir`` when it was made with exactly these settings (``scoring`` as in
    :func:`run_benchmark`; its scored rows and what it states about its inputs), else None: what a whole suite
    rerun reuses instead of relighting again. A killed run (rows still partial) is not finished: it is resumed."""
    out_dir = Path(out_dir)
    if not (out_dir / tables.PER_IMAGE_CSV).is_file() or (out_dir / PARTIAL_CSV).is_file():
        return None
    want = run_settings(store, method, protocols, scoring or Scoring.of(store), limit=limit,
                        oracle_light=oracle_light, oracle_shadow=oracle_shadow, shard=None)
    if provenance.differences(read_json_mapping(out_dir / SETTINGS), provenance.plain(want)):
        return None
    try:
        stated = json.loads((out_dir / provenance.PROVENANCE).read_text())
    except (OSError, ValueError):
        return None
    return BenchmarkResult(records=tables.read_records(out_dir / tables.PER_IMAGE_CSV), provenance=stated)


def run_settings(store: EncodingStore, method: Method, protocols: Sequence[str], scoring: Scoring, *,
                 limit: int | None, oracle_light: bool, oracle_shadow: bool, shard: str | None) -> dict[str, Any]:
    """What decides a benchmark run's rows (compared when a run resumes into the same folder). ``target_sun``
    counts only where it changes a relight: fitted lights and a method that reads a shadow map."""
    relighter = getattr(method, "relighter", None)
    model = getattr(relighter, "model", None)
    marched = {"target_sun": scoring.target_sun} if not oracle_light and _marches(method) else {}
    return {"method": method.name, "model": provenance.model_identity(model) if model is not None else None,
            "sampler": relighter.spec.to_config() if getattr(relighter, "spec", None) is not None else None,
            "precision": relighter.runtime.precision if relighter is not None else None,
            "store": provenance.store_identity(store), "versions": dict(getattr(store, "versions", {}) or {}),
            "protocols": list(protocols), "limit": limit, "oracle_light": bool(oracle_light),
            "oracle_shadow": bool(oracle_shadow), "rule": scoring.rule, "score_mask": scoring.score_mask,
            "shard": shard, **marched}


def _marches(method: Method) -> bool:
    """Whether ``method`` reads a target shadow map (its relights depend on where the map is marched)."""
    relighter = getattr(method, "relighter", None)
    return relighter is not None and "shadow_map" in getattr(relighter, "model_inputs", ())


@dataclass
class _Run:
    """What every pair of one run shares. ``columns``: the extra CSV columns; ``exact``: the store holds exact
    lights; ``source_light``: the method's own source-light fit (its error is measured too)."""

    store: EncodingStore
    method: Method
    out_dir: Path
    scoring: Scoring
    lights: Lights
    extras: PairExtras
    columns: list[str]
    oracle_shadow: bool
    exact: bool
    source_light: Callable[[StoredFace], np.ndarray] | None
    save_images: bool


def _run(run: _Run, result: BenchmarkResult, protocols: Sequence[str], *, limit: int | None, shard: str | None,
         grid_pairs: int, progress: bool) -> BenchmarkResult:
    """Every pair relit and scored (or resumed from the partial CSV), then the run's outputs written."""
    store, method, out_dir = run.store, run.method, run.out_dir
    rule, score_mask = run.scoring.rule, run.scoring.score_mask
    done = _scored_so_far(out_dir, method.name, rule)
    selected = {proto: list(sharding.select(pairs, shard, key=lambda p: p.id))
                for proto, pairs in load_pairs(store, protocols, limit).items()}
    batched = BatchedRelights(store, method, run.lights, run.oracle_shadow,
                              [(PROTOCOLS[proto], pair) for proto, pairs in selected.items() for pair in pairs
                               if (PROTOCOLS[proto], pair.id) not in done])
    for proto, pairs in selected.items():
        short = PROTOCOLS[proto]
        grid_rows: list[list[np.ndarray]] = []
        scorer = metrics.relight_metrics(rule)  # this run's scores of the protocol (rows resumed are not in it)
        for pair in tqdm(pairs, desc=f"{method.name} {proto}", disable=not progress):
            light, shadow = run.lights.for_pair(pair, oracle_shadow=run.oracle_shadow)
            result.provenance.setdefault("target c", run.lights.shadow_note)
            if run.exact:  # the fitted lights' errors
                result.light_errors += [{"protocol": short, **e}
                                        for e in run.lights.errors(pair, light, run.source_light)]
            png = out_dir / "relit" / proto / f"{pair.id}.png"
            want_grid = len(grid_rows) < grid_pairs
            prev = done.get((short, pair.id))
            source, target = StoredFace(store, pair.source), StoredFace(store, pair.target)  # each read once
            if prev is not None and (not want_grid or prev.status != "ok" or png.is_file()):
                # scored before the run was killed: not redone
                rec, relit = prev, _read_png(png) if want_grid and prev.status == "ok" else None
            else:
                rec, relit = _relight_and_score(run, pair, source, target, light, shadow, scorer,
                                                batched.get(short, pair))
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


def _start(store: EncodingStore, method: Method, out_dir: Path, scoring: Scoring, *, oracle_light: bool,
           oracle_shadow: bool, estimator: LightFit | None, save_images: bool) -> tuple[_Run, BenchmarkResult]:
    """The run's shared inputs and its result so far: what it states about its inputs, no rows yet."""
    doc = protocols_doc(store)
    exact = bool(doc.get("exact_lights", True))
    if oracle_light and not exact:
        raise errors.UserError(f"oracle_light=true but {store.root} holds no exact lights (a "
                               f"{doc.get('dataset', 'photo')} store); drop oracle_light")
    estimator = estimator or LightFit()
    extras = PairExtras(store, scoring.score_mask, fit=estimator)
    result = BenchmarkResult(records=[], provenance={
        "target light": "exact (oracle_light)" if oracle_light else "fitted to the light-source image (LightFit)",
        "target maps": getattr(method, "target_maps", "none (the method reads no light-dependent map)"),
        "data set": str(doc.get("dataset", "synthfaces")), "metrics rule": scoring.rule,
        "score mask": scoring.score_mask})
    result.provenance.update({**extras.provenance(), "store": f"{store.root} ({provenance.store_identity(store)})"})
    result.notes = list(extras.notes)
    # Methods that fit their source light (the Lambertian baseline) are scored on it too, through their own door.
    fits = method.needs_light_fit and getattr(method, "estimator", None) is not None
    source_light = method.source_light if fits else None
    marches = _marches(method) and not oracle_light
    lights = Lights(store, None if oracle_light else estimator,
                    sun_from_shadows=marches and scoring.target_sun == "shadows")
    if marches:
        result.provenance["target sun"] = ("found from the light-source image's cast shadows (render.sun_fit)"
                                           if scoring.target_sun == "shadows" else "the fitted light's radiance peak")
    run = _Run(store, method, out_dir, scoring, lights, extras,
               [*extras.metrics(), *extras.strata()], oracle_shadow, exact, source_light, save_images)
    return run, result


def _relight_and_score(run: _Run, pair: Pair, source: StoredFace, target: StoredFace, light: np.ndarray,
                       shadow: float | None, scorer, batched: tuple[np.ndarray, float] | None = None
                       ) -> tuple[tables.Record, np.ndarray | None]:
    """One pair relit by the method and scored: its row and relit image, or (a bad pair) its failed row and None.
    Its source is read whole and checked once: here (the method takes its encodings from it), or for ``batched``
    (its relit image and seconds, made in a batch) by :class:`~difareli.evaluation.batched.BatchedRelights`; the
    target light and shadow are checked by the method's relight (a model's ``Targets``)."""
    name, short = run.method.name, PROTOCOLS[pair.protocol]
    rule, mask = run.scoring.rule, run.scoring.score_mask
    gt = target.read(["image", mask])
    start = time.perf_counter()
    # Only a bad pair is a failed row, reported as failed, never a score: a non-finite input or result, or
    # a record whose file is corrupt. Other user errors (a missing record or encoding, an image too small
    # to score, a method's wrong output) hold for every pair: they stop the run with their message.
    try:
        if batched is None:
            errors.check_record(source.read(), pair.source, run.store.root)
            relit = run.method.relight(source, light, shadow, target=target, target_sun=run.lights.sun(pair))
            seconds = time.perf_counter() - start
        else:
            relit, seconds = batched
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
    if relit is not None and run.save_images:
        viz.save_png(relit, png)
    header = tables.header(run.columns)  # the row after the image: a resumed run finds both
    append_csv_row(run.out_dir / PARTIAL_CSV, header, dict(zip(header, tables.record_row(rec, extra=run.columns))))


def write_outputs(result: BenchmarkResult, out_dir: Path, caption: str | None = None) -> dict[str, Path]:
    """Per-image CSV, summary tables (Markdown with the light-estimation errors, CSV, LaTeX), light CSV; each
    written atomically (a full disk is one line naming the file and leaves the previous one whole)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    table = result.table
    paths = {"per_image": out_dir / tables.PER_IMAGE_CSV}
    with atomic_path(paths["per_image"]) as tmp:
        tables.write_records(tmp, result.records)
    md = table.to_markdown()
    if result.provenance:  # every table says which inputs were estimated and which were oracle (and the mask)
        md = "Inputs: " + "; ".join(f"{k}: {v}" for k, v in result.provenance.items()) + "\n\n" + md
        paths["provenance"] = write_json_atomic(out_dir / "provenance.json", result.provenance)
    if result.light_errors:
        md += "\nLight estimation (relative irradiance error on the ground truth's face normals):\n\n"
        md += result.light_summary()
    paths["summary_md"] = write_text_atomic(out_dir / "summary.md", md)
    paths["summary_csv"] = write_text_atomic(out_dir / "summary.csv", table.to_csv())
    paths["summary_tex"] = write_text_atomic(out_dir / "summary.tex", table.to_latex(caption=caption))
    if result.light_errors:
        cols = ["protocol", "record_id", "light", "from", "rel_error", "rel_error_gain_free"]
        lines = [",".join(cols)] + [",".join(str(e[c]) for c in cols) for e in result.light_errors]
        paths["light_csv"] = write_text_atomic(out_dir / LIGHT_CSV, "\n".join(lines) + "\n")
    return paths
