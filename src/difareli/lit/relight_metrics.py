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

The pairs and their target conditions are prepared once, at fit start. Under DDP every process relights its share
of the sources and the Metrics' summed states reduce over all of them. A store without SynthFaces light groups in its
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

from difareli.evaluation import metrics
from difareli.utils import viz
from difareli.diffusion.spec import SamplerSpec, as_spec
from difareli.data.inputs import condition_tensors, image_to_tensor, read_record, relight_reads
from difareli.data.protocols import PROTOCOLS, protocol_pairs
from difareli.lit.logging import log_image
from difareli.relight.relightable import OnePassRelightable, Relightable, model_inputs
from difareli.errors import UserError
from difareli.evaluation.extras import PairExtras
from difareli.lighting.light_fit import LightFit
from difareli.relight.core import relight
from difareli.relight.targets import retarget, target_shadow_of
from difareli.runtime.core import Runtime



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
    (``auto``, as every relighting command: bf16 where the hardware has it natively; ``fp32`` | ``bf16``).
    """

    def __init__(self, pairs: int = 4, every_n_steps: int | None = None, sampler: Any = "unipc", steps: int | None = 10,
                 rule: str | None = None, precision: str = "auto", grid: bool = True, enabled: bool = True,
                 extras: bool = True):
        self.spec: SamplerSpec = as_spec(sampler, steps=steps)  # a bad sampler fails before training
        self.rule = metrics.check_rule(rule)
        if precision not in ("auto", "fp32", "bf16"):
            raise UserError(f"callbacks.relight_metrics.precision={precision!r} is not auto, fp32 or bf16")
        if every_n_steps is not None and (not isinstance(every_n_steps, int) or every_n_steps < 1):
            raise UserError(f"callbacks.relight_metrics.every_n_steps={every_n_steps!r} must be null or an int >= 1")
        self.pairs, self.every_n_steps, self.precision = int(pairs), every_n_steps, precision
        self.grid, self.enabled, self.extras = bool(grid), bool(enabled), bool(extras)
        self.scorer = None  # difareli.evaluation.extras.PairExtras of the store, made at fit start
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
        pairs = validation_pairs(store, split, self.pairs)
        if not pairs:
            self._disable(f"store {store.root} has no SynthFaces light groups in its {split!r} split")
            return
        rank, world = trainer.global_rank, trainer.world_size
        self.cases = [self._prepare(store, pl_module, p) for p in pairs[rank::world]]
        if self.extras:
            self.scorer = PairExtras(store)
        self._clock = time.perf_counter()

    def _disable(self, why: str) -> None:
        warnings.warn(f"relight metrics off: {why}", stacklevel=2)
        self.enabled = False

    def _prepare(self, store, model, pair: Mapping[str, str]) -> dict[str, Any]:
        """The source's condition, both protocols' target conditions, the ground truth and its mask."""
        names = relight_reads(model_inputs(model))
        arrays = read_record(store, pair["source"], names)
        fit, targets, lights = LightFit(), [], []
        for proto in PROTOCOLS.values():
            light = fit.from_store(store, pair[proto])
            shadow, _ = target_shadow_of(store, pair[proto])
            targets.append(retarget(arrays, model_inputs(model), light, shadow))
            lights.append(light)
        gt = store.read(pair["target"], ["image", "face_mask"])
        return {"pair": dict(pair), "lights": lights, "x0": image_to_tensor(arrays["image"])[None],
                "source": condition_tensors(model, [arrays]), "targets": condition_tensors(model, targets),
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

    @torch.no_grad()
    def evaluate(self, trainer: L.Trainer, pl_module) -> dict[str, float]:
        """Relight the prepared pairs with ``pl_module``'s current weights; log and return the metrics."""
        since = time.perf_counter() - (self._clock or time.perf_counter())
        t0 = time.perf_counter()
        dev = pl_module.device
        runtime = Runtime(device="cpu" if dev.type == "cpu" else str(dev), precision=self.precision)
        scores = {p: metrics.relight_metrics(self.rule).to(dev) for p in PROTOCOLS.values()}
        extra: dict[str, dict[str, metrics.FiniteMean]] = {p: {} for p in PROTOCOLS.values()}
        was_training = pl_module.training
        pl_module.eval()
        rows: dict[str, list] = {p: [] for p in PROTOCOLS.values()}
        to = lambda c: tuple(None if v is None else v.to(dev) for v in c)  # noqa: E731
        for case in self.cases:
            out = relight(pl_module, case["x0"].to(dev), to(case["source"]), to(case["targets"]),
                          None if isinstance(pl_module, OnePassRelightable) else self.spec, runtime=runtime)
            images = [viz.to_uint8(x.clamp(-1, 1)) for x in out]  # scored as saved, like difareli-benchmark
            relit = metrics.unit_tensor(np.stack(images)).to(dev)
            for k, proto in enumerate(PROTOCOLS.values()):
                scores[proto].update(relit[k:k + 1], case["gt"].to(dev), case["mask"].to(dev))
                if self.scorer is not None:  # the benchmark's extra scores of the same uint8 image
                    ex, _ = self.scorer(images[k], case["pair"]["source"], case["pair"]["target"], case["lights"][k])
                    for name, v in ex.items():
                        extra[proto].setdefault(name, metrics.FiniteMean().to(dev)).update(v)
                rows[proto].append([viz.to_uint8(case["x0"][0]), images[k], viz.to_uint8(case["gt"][0] * 2 - 1)])
        pl_module.train(was_training)
        values = {f"val/{k}/{proto}": float(v) for proto, coll in scores.items() for k, v in coll.compute().items()}
        values.update({f"val/{k}/{proto}": float(m.compute()) for proto, ms in extra.items() for k, m in ms.items()})
        seconds = time.perf_counter() - t0
        for name, v in values.items():
            if math.isfinite(v):
                pl_module.log(name, v, on_step=False, on_epoch=True, batch_size=1)
        pl_module.log("perf/relight_metrics_s", seconds, on_step=False, on_epoch=True, batch_size=1)
        step = trainer.global_step
        if self.grid and trainer.is_global_zero and rows["same"]:
            path = Path(trainer.default_root_dir) / "grids" / f"relight_metrics_step{step:07d}.png"
            log_image(trainer, "val/relight_metrics_grid", viz.save_png(viz.grid(rows["same"] + rows["different"]),
                                                                         path))
        relights = len(self.cases) * len(PROTOCOLS)
        how = "one pass" if isinstance(pl_module, OnePassRelightable) else f"{self.spec.name}-{self.spec.steps}"
        share = f" = {100 * seconds / since:.1f}% of the {since:.0f} s since the last one" if since > 0 else ""
        if trainer.is_global_zero:
            print(f"relight metrics at step {step}: {relights} relights ({how}, rule {self.rule}) in {seconds:.2f} s"
                  f"{share}; " + ", ".join(f"{k} {v:.4f}" for k, v in values.items()))
        self.history.append({"step": step, "seconds": seconds, "since": since, **values})
        self._last_step, self._clock = step, time.perf_counter()
        return values
