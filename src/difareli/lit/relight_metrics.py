"""Relighting quality measured while training: the benchmark's protocols on a few fixed validation pairs.

:class:`RelightMetrics` relights ``pairs`` sources of the store's validation split under both protocols of SPEC 11
(the target light fitted to the same subject's image under the target light, and to another subject's of the same
light group, as difareli-benchmark does on the test split) with a few-step sampler (one network pass for a
one-pass student), and logs ``val/<metric>/<protocol>`` (``val/dssim/same``, ``val/lpips/different``, ...) under
the metric rule (``paper`` by default) through the torchmetrics Metrics of :mod:`difareli.evaluation.metrics`, plus an
input | relit | ground truth grid, to every configured logger. It runs at the start of a validation (after the EMA
callback has swapped its average in) once ``every_n_steps`` have passed since its last run (null: every
validation), and prints what one evaluation cost against the training wall time since the previous one.
With ``extras`` (default) it also logs the metrics beyond DSSIM / MSE / LPIPS that difareli-benchmark writes
(:mod:`difareli.evaluation.extras`: ``val/identity_input/same``, ``val/light_angle/different``,
``val/shadow_adherence/same``, ...; each where the store and the installed extras allow it, a metric undefined on
every pair is not logged).

The module relights through the relight door (:class:`~difareli.relight.relighter.Relighter` around the live
module: its sources read and checked there, ``relight_many`` inverting every source once for both of its targets),
and its targets are the benchmark's (:class:`~difareli.evaluation.pairs.Lights`: the light fitted to the
light-source image, its shadow strength c and, for a model that reads shadow maps, the key sun its map is marched
toward): the validation numbers are the benchmark's computation on other records. A relight that is not finite
skips that evaluation with a warning; training goes on.

The pairs and their targets are prepared once, at fit start. Under DDP every process relights its share
of the sources (at least one: a process without one would never join the reduction) and the Metrics' summed states
reduce over all of them; a skip is decided by all processes together. A store without SynthFaces light groups in its
validation split (a photo store) gets one warning and no relight metrics.
"""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path
from typing import Any, Mapping

import lightning as L
import numpy as np
import torch

from difareli import errors
from difareli.checkpoints.loading import LoadedCheckpoint
from difareli.data.protocols import PROTOCOLS, protocol_pairs
from difareli.diffusion.spec import SamplerSpec, as_spec
from difareli.evaluation import metrics
from difareli.evaluation.extras import PairExtras
from difareli.evaluation.pairs import Lights, Pair, StoredFace
from difareli.lighting.light_fit import LightFit
from difareli.lit.logging import log_image
from difareli.relight.relightable import OnePassRelightable, Relightable
from difareli.relight.relighter import Relighter
from difareli.relight.targets import Targets
from difareli.render.sun_fit import TARGET_SUNS
from difareli.runtime.core import Runtime
from difareli.utils import viz


def validation_pairs(store, split: str, n: int) -> list[dict[str, str]]:
    """``n`` sources of ``split`` (evenly spread), each with a target record and the light source of both
    protocols: ``{"source", "target", "same", "different"}`` (record ids); [] without SynthFaces light groups."""
    meta = store.store_meta
    group, lights = meta.get("light_group_size"), meta.get("lights")
    ids = set(store.ids(split=split))
    names = {str(store.meta(r).get("subject", "")) for r in ids}
    subjects = sorted(int(s[1:]) for s in names if s[:1] == "s" and s[1:].isdigit())
    if not group or not lights or not subjects:
        return []
    diff = [p for p in protocol_pairs(subjects, int(lights), int(group))["different_subject"]
            if {p["source"], p["light_source"], p["target"]} <= ids]
    seen, out = set(), []
    for p in diff:  # one light source per (source, target): the first partner
        if (p["source"], p["target"]) not in seen:
            seen.add((p["source"], p["target"]))
            out.append({"source": p["source"], "target": p["target"], "same": p["target"],
                        "different": p["light_source"]})
    if n < len(out):
        out = [out[i] for i in np.unique(np.linspace(0, len(out) - 1, n).round().astype(int))]
    return out


class RelightMetrics(L.Callback):
    """Log ``val/{dssim,mse,lpips}/{same,different}`` and a relight grid during fit (see the module docstring).

    ``sampler``/``steps``: a preset name, a sampler config or a spec (diffusion models only); ``rule``: the metric
    rule (``paper`` | ``composite``); ``precision``: the relights' :class:`~difareli.runtime.core.Runtime` precision
    (``auto``, as every relighting command: bf16 where the hardware has it natively; ``fp32`` | ``bf16``);
    ``target_sun``: where a model that reads shadow maps has its target maps marched, as difareli-benchmark's
    option of that name (``shadows``: toward the key sun found from the light-source image's cast shadows;
    ``peak``: the fitted light's radiance peak).
    """

    def __init__(self, pairs: int = 4, every_n_steps: int | None = None, sampler: Any = "unipc", steps: int | None = 10,
                 rule: str | None = None, precision: str = "auto", grid: bool = True, enabled: bool = True,
                 extras: bool = True, target_sun: str = "shadows"):
        self.spec: SamplerSpec = as_spec(sampler, steps=steps)  # a bad sampler fails before training
        self.rule = metrics.check_rule(rule)
        key = "callbacks.relight_metrics"
        errors.check_choice(precision, f"{key}.precision", ("auto", "fp32", "bf16"))
        self.target_sun = errors.check_choice(target_sun, f"{key}.target_sun", TARGET_SUNS)
        if every_n_steps is not None and (not isinstance(every_n_steps, int) or every_n_steps < 1):
            raise errors.UserError(f"{key}.every_n_steps={every_n_steps!r} must be null or an int >= 1")
        self.pairs, self.every_n_steps, self.precision = int(pairs), every_n_steps, precision
        self.grid, self.enabled, self.extras = bool(grid), bool(enabled), bool(extras)
        self.scorer = None  # difareli.evaluation.extras.PairExtras of the store, made at fit start
        self.relighter: Relighter | None = None  # the training module behind the relight door, made at fit start
        self.cases: list[dict[str, Any]] = []
        self.history: list[dict[str, Any]] = []
        self._last_step: int | None = None
        self._clock: float | None = None

    # ------------------------------------------------------------------------------------------- preparation
    def on_fit_start(self, trainer: L.Trainer, pl_module) -> None:
        if not self.enabled or trainer.fast_dev_run:
            self.enabled = False
            return
        store = getattr(trainer.datamodule, "store", None)
        if store is None or not isinstance(pl_module, Relightable):
            self._disable("no encodings store on the datamodule or the module is not a Relightable")
            return
        split = getattr(trainer.datamodule, "val_split", "val")
        rank, world = trainer.global_rank, trainer.world_size
        # At least one pair per process: a process without one would never join the metrics' reduction (a hang).
        # Every process computes the same list, so they all decide alike.
        pairs = validation_pairs(store, split, max(self.pairs, world))
        if not pairs:
            self._disable(f"store {store.root} has no SynthFaces light groups in its {split!r} split")
            return
        if len(pairs) < world:
            self._disable(f"its {split!r} split gives {len(pairs)} validation pair(s) for {world} processes")
            return
        self.prepare(store, pl_module, pairs[rank::world], step=trainer.global_step)
        self._clock = time.perf_counter()

    def _disable(self, why: str) -> None:
        warnings.warn(f"relight metrics off: {why}", stacklevel=2)
        self.enabled = False

    def prepare(self, store, model, pairs, step: int = 0) -> None:
        """The relighter of ``model`` (its live weights: nothing is copied or cached between evaluations) and,
        per pair, the source read and checked through it, both protocols' targets as difareli-benchmark makes
        them (:class:`~difareli.evaluation.pairs.Lights`: the light fitted to the light-source image, its c, its
        key sun), the ground truth and its mask. Once per fit: the pairs are fixed."""
        dev = model.device
        runtime = Runtime(device="cpu" if dev.type == "cpu" else str(dev), precision=self.precision)
        self.relighter = Relighter(LoadedCheckpoint.of_module(model, step), self.spec, runtime=runtime,
                                   batch_size=max(1, len(pairs)))
        marches = "shadow_map" in self.relighter.model_inputs
        fit = LightFit()
        lights = Lights(store, fit, sun_from_shadows=marches and self.target_sun == "shadows")
        self.cases = [self._prepare(store, lights, p) for p in pairs]
        self.scorer = PairExtras(store, fit=fit) if self.extras else None

    def _prepare(self, store, lights: Lights, pair: Mapping[str, str]) -> dict[str, Any]:
        source = self.relighter.source(store, pair["source"])
        chosen = [Pair(proto, pair["source"], pair[short], pair["target"]) for proto, short in PROTOCOLS.items()]
        found = [lights.for_pair(p) for p in chosen]
        targets = Targets.of([light for light, _ in found], [c for _, c in found], f"pair {pair['source']}",
                             suns=[lights.sun(p) for p in chosen])
        gt = store.read(pair["target"], ["image", "face_mask"])
        return {"pair": dict(pair), "source": source, "targets": targets,
                "gt": metrics.unit_tensor(gt["image"]),
                "mask": torch.from_numpy(np.array(gt["face_mask"], dtype=bool))[None]}

    # -------------------------------------------------------------------------------------------- evaluation
    def _due(self, trainer: L.Trainer) -> bool:
        if not self.enabled or not self.cases or trainer.sanity_checking:
            return False
        n = self.every_n_steps
        return self._last_step is None or not n or trainer.global_step - self._last_step >= int(n)

    def on_validation_epoch_start(self, trainer: L.Trainer, pl_module) -> None:
        if self._due(trainer):
            self.evaluate(trainer, pl_module)

    def _relight(self, pl_module) -> tuple[np.ndarray | None, str | None]:
        """The prepared pairs relit by the module's current weights through the relight door's many-sources call
        (S, 2, H, W, 3) uint8; (None, why) where a relight is not finite (a diverging or bf16-overflowing model:
        the metrics of that evaluation are not logged, and training goes on)."""
        if self.relighter.model is not pl_module:  # its sources were checked against that module's inputs
            raise ValueError("RelightMetrics.evaluate takes the module it was prepared with (prepare / on_fit_start)")
        was_training = pl_module.training
        pl_module.eval()
        try:
            return self.relighter.relight_many([c["source"] for c in self.cases],
                                               [c["targets"] for c in self.cases]), None
        except errors.NonFiniteError as e:
            return None, str(e).splitlines()[0]
        finally:
            pl_module.train(was_training)

    @torch.no_grad()
    def evaluate(self, trainer: L.Trainer, pl_module) -> dict[str, float]:
        """Relight the prepared pairs with ``pl_module``'s current weights; log and return the metrics."""
        since = time.perf_counter() - (self._clock or time.perf_counter())
        t0 = time.perf_counter()
        step = trainer.global_step
        relit, why = self._relight(pl_module)
        skip = relit is None
        if getattr(trainer, "world_size", 1) > 1:  # every process skips or none does: each joins the reduction
            skip = trainer.strategy.reduce_boolean_decision(skip, all=False)
        if skip:
            why = why or "a relight of another process is not finite"
            warnings.warn(f"relight metrics at step {step} skipped: {why}", RuntimeWarning, stacklevel=2)
            self._last_step, self._clock = step, time.perf_counter()
            return {}
        dev = pl_module.device
        scores = {p: metrics.relight_metrics(self.rule).to(dev) for p in PROTOCOLS.values()}
        extra: dict[str, dict[str, metrics.FiniteMean]] = {p: {} for p in PROTOCOLS.values()}
        rows: dict[str, list] = {p: [] for p in PROTOCOLS.values()}
        for case, images in zip(self.cases, relit):  # scored as saved (uint8), like difareli-benchmark
            relit_unit = metrics.unit_tensor(images).to(dev)
            for k, proto in enumerate(PROTOCOLS.values()):
                scores[proto].update(relit_unit[k:k + 1], case["gt"].to(dev), case["mask"].to(dev))
                if self.scorer is not None:  # the benchmark's extra scores of the same uint8 image
                    ex, _ = self.scorer(images[k], *(StoredFace(self.scorer.store, case["pair"][r])
                                                     for r in ("source", "target")), case["targets"].lights[k])
                    for name, v in ex.items():
                        extra[proto].setdefault(name, metrics.FiniteMean().to(dev)).update(v)
                rows[proto].append([case["source"].arrays["image"], images[k],
                                    viz.to_uint8(case["gt"][0] * 2 - 1)])
        values = {f"val/{k}/{proto}": float(v) for proto, coll in scores.items() for k, v in coll.compute().items()}
        values.update({f"val/{k}/{proto}": float(m.compute()) for proto, ms in extra.items() for k, m in ms.items()})
        seconds = time.perf_counter() - t0
        for name, v in values.items():
            if math.isfinite(v):
                pl_module.log(name, v, on_step=False, on_epoch=True, batch_size=1)
        pl_module.log("perf/relight_metrics_s", seconds, on_step=False, on_epoch=True, batch_size=1)
        if self.grid and trainer.is_global_zero and rows["same"]:
            path = Path(trainer.default_root_dir) / "grids" / f"relight_metrics_step{step:07d}.png"
            log_image(trainer, "val/relight_metrics_grid", viz.save_png(viz.grid(rows["same"] + rows["different"]),
                                                                         path))
        relights = len(self.cases) * len(PROTOCOLS)
        share = f" = {100 * seconds / since:.1f}% of the {since:.0f} s since the last one" if since > 0 else ""
        if trainer.is_global_zero:
            print(f"relight metrics at step {step}: {relights} relights ({self._how()}, rule {self.rule}) in "
                  f"{seconds:.2f} s{share}; " + ", ".join(f"{k} {v:.4f}" for k, v in values.items()))
        self.history.append({"step": step, "seconds": seconds, "since": since, **values})
        self._last_step, self._clock = step, time.perf_counter()
        return values

    def _how(self) -> str:
        if isinstance(self.relighter.model, OnePassRelightable):
            return "one pass"
        return f"{self.spec.name}-{self.spec.steps}"
