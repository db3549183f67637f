"""A relighting model against the two baselines (returning the input unchanged, the Lambertian ratio image) on a
SynthFaces store's test pairs of both protocols, and the facts a model card states about that measurement.

The one home of this comparison for ``difareli-demo``, ``scripts/release_reference.py`` (the shipped references'
model cards) and ``scripts/gpu_train_reference.py``: every method runs through
:class:`difareli.evaluation.benchmark.BenchmarkJob` with one shared light estimator, so the three rows see the same
fitted target lights, and the rows merge into one :class:`~difareli.evaluation.tables.Table`.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from difareli.evaluation import tables
from difareli.evaluation.benchmark import BenchmarkJob, BenchmarkResult
from difareli.data.protocols import PROTOCOLS
from difareli.data.store import EncodingStore
from difareli.evaluation.baselines import DiffusionMethod, Identity, LambertianRatio
from difareli.lighting.light_fit import LightFit

#: Both evaluation protocols: (i) relit toward the same subject's other light, (ii) toward another subject's light.


@dataclass
class Comparison:
    """What :func:`compare_to_baselines` measured."""

    #: identity, Lambertian ratio image, the model: one row each, both protocols (mean ± SE)
    table: tables.Table
    #: per method name, its benchmark run (records, provenance of the inputs, light-fit errors, written paths)
    runs: dict[str, BenchmarkResult] = field(default_factory=dict)
    #: wall seconds per method name (its run) and "total" (the model's loading included)
    seconds: dict[str, float] = field(default_factory=dict)
    #: the model card's facts: pairs (per protocol), protocols, methods, sampler, runtime, inputs, seconds, table
    facts: dict[str, Any] = field(default_factory=dict)

    @property
    def records(self) -> list[tables.Record]:
        """Every scored image of every method, in run order."""
        return [r for run in self.runs.values() for r in run.records]

    def card_benchmark(self, pairs_from: str = "") -> str:
        """The model card's benchmark section: how many pairs (``pairs_from`` says of what, e.g. "of the training
        store's test split (unseen subjects)"), which inputs were estimated, sampler, runtime, seconds, then the
        table."""
        f = self.facts
        counts = sorted(set(f["pairs"].values()))
        pairs = (f"{counts[0]} test pairs per protocol" if len(counts) == 1 else
                 "test pairs " + ", ".join(f"{n} ({p})" for p, n in f["pairs"].items()))
        return (f"{pairs}{' ' + pairs_from if pairs_from else ''}, {f['inputs']}, {f['sampler']}, {f['runtime']} "
                f"({f['seconds']:.0f} s):\n\n{f['table']}")


def compare_to_baselines(store: EncodingStore | str | Path, checkpoint: Any, sampler: Mapping[str, Any],
                         out_dir: str | Path, *, pairs: int | None, runtime: Mapping[str, Any] | None = None,
                         protocols: Sequence[str] = PROTOCOLS, oracle_light: bool = False,
                         oracle_shadow: bool = False, grid_pairs: int = 0, save_images: bool = False,
                         progress: bool = False, reuse: bool = False, model_name: str | None = None) -> Comparison:
    """Benchmark identity, the Lambertian ratio image and ``checkpoint`` (a path, a shipped name or a loaded
    checkpoint, relit with ``sampler`` under ``runtime``) on at most ``pairs`` pairs per protocol of ``store``.

    Target lights are fitted to the light-source images and the target c is what a user has (the benchmark's
    defaults), unless ``oracle_light`` / ``oracle_shadow``; the card facts say which. Each method's run is written
    under ``out_dir/<method name>`` (resumable, as a :class:`~difareli.evaluation.benchmark.BenchmarkJob` is);
    ``reuse``: a method's finished run there with the same settings is read back instead of relit again.
    ``model_name`` names the model's row (``<model_name>/<sampler>``; default: its config's variant name)."""
    start = time.perf_counter()
    store = store if isinstance(store, EncodingStore) else EncodingStore.open(store)
    fit = LightFit()  # one estimator: every row is scored under the same fitted target lights
    model = DiffusionMethod(checkpoint, sampler, runtime=runtime, model_name=model_name)
    runs, seconds = {}, {}
    for method in (Identity(), LambertianRatio(estimator=fit), model):
        t0 = time.perf_counter()
        where = Path(out_dir) / slug(method.name)
        job = BenchmarkJob.of(store, method, protocols, where, limit=pairs, oracle_light=oracle_light,
                              oracle_shadow=oracle_shadow, estimator=fit, grid_pairs=grid_pairs,
                              save_images=save_images, progress=progress)
        done = job.finished() if reuse else None
        runs[method.name] = done or job.run()
        # A reused run's seconds are its relights' own (what the rows' s/img says), not this reading of them.
        seconds[method.name] = (sum(r.seconds for r in done.records if r.seconds == r.seconds) if done
                                else time.perf_counter() - t0)
    seconds["total"] = sum(seconds.values()) if reuse else time.perf_counter() - start
    table = tables.summarize([r for run in runs.values() for r in run.records])
    own, rt, spec = runs[model.name], model.relighter.runtime, model.relighter.spec
    light = ("exact target lights (oracle)" if oracle_light
             else "target lights fitted to the light-source images (not the oracle)")
    facts = {"pairs": dict(Counter(r.protocol for r in own.records)), "protocols": list(protocols),
             "methods": list(runs), "model": model.name,
             "sampler": "one network pass" if model.one_pass else f"{spec.name}-{spec.steps}",
             "runtime": f"{rt.precision} on {rt.torch_device.type}" + (", compiled" if rt.compile else "")
                        + (", CUDA graphs" if rt.graphs_active else ""),
             "inputs": f"{light}, target c: {own.provenance.get('target c') or 'none'}",
             "seconds": seconds["total"], "table": table.to_markdown()}
    return Comparison(table=table, runs=runs, seconds=seconds, facts=facts)


def slug(name: str) -> str:
    """A method name as a folder name (``difareli_pp/unipc-20`` -> ``difareli_pp_unipc-20``)."""
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)
