"""DiFaReli++'s difference-method shadow maps from a trained DiFaReli (paper Sec. IV-A; issue 12).

For every record: relight it with its own light at the largest and at the smallest shadow strength of the
training split (``c_max``, ``c_min``), through the relighting core (any sampler; records inverted in batches,
both targets decoded in one batch). The **difference** is ``Y(relit at c_min) - Y(relit at c_max)`` (Rec. 709
luminance, images in [0, 1]): positive where the stronger shadow darkened the face. Then

1. **one global threshold** over every difference value on the mesh of every record (Otsu's between-class
   variance maximum on a 256-bin histogram; or a given number),
2. a ``median`` x ``median`` **median filter** of the binary map (removes speckle; a 3x3 one also drops the
   corners of a rectangle: 4 of its 9 neighbours are in),
3. times the record's **normalised c** (``encodings.normalise_c`` of its stored ``shadow``): the
   ``shadow_map`` encoding's definition. Pixels off the mesh (``depth == 0``, when stored) are 0.

The raw differences are kept as the derived version ``shadow_map@diffraw-<hash>`` (resumable: a killed run
redoes only records without it), the maps as ``shadow_map@<version>`` (:mod:`difareli.derived`), both with their
provenance (checkpoint, sampler, c range, threshold rule and value, median size) in the store header.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from difareli import derived, encodings, errors, imageops
from difareli.diffusion.relight import Inversion
from difareli.imageops import median_mask
from difareli.inputs import condition_tensors, image_to_tensor, relight_reads
from difareli.relightable import OnePassRelightable, model_inputs
from difareli.relighting import invert_image, relight
from difareli.targets import retarget


def c_range(store, split: str = "train", quantile: float = 0.01) -> tuple[float, float]:
    """``(c_min, c_max)`` of the stored ``shadow`` over ``split`` (all records if the split is empty): the
    ``quantile`` and ``1 - quantile`` quantiles. 0 is the paper's strict min and max; the default 0.01 keeps an
    estimator's outliers (one record of 3,200 at c = -39.6 in SynthFaces v2) from setting the range, where the
    DiFaReli never saw such a c (docs/shadow_maps.md: pooled IoU 0.06 -> 0.12)."""
    if not 0.0 <= float(quantile) < 0.5:
        raise errors.UserError(f"c_quantile={quantile} is out of range; use a number in [0, 0.5), e.g. 0.01")
    ids = store.ids(split=split) or store.ids()
    c = np.array([encodings.shadow_logit(store.read(r, ["shadow"])) for r in ids])
    errors.check_finite(c, f"shadow c of the {split} split of {store.root}")
    lo, hi = (float(v) for v in np.quantile(c, [quantile, 1.0 - quantile])) if c.size else (0.0, 0.0)
    if hi <= lo:
        raise errors.UserError(f"the {split} split of {store.root} has no spread of shadow c between its {quantile} "
                               f"and {1 - quantile} quantiles ({lo} to {hi}); the difference method needs records "
                               "with and without cast shadows")
    return lo, hi


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of ``values``: the bin edge maximising the between-class variance (values > t: class 1);
    the middle of the maximising edges when several tie (empty bins between two modes)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    v = v[np.isfinite(v)]
    if v.size == 0 or v.max() == v.min():
        raise ValueError("Otsu's threshold needs at least two distinct finite values")
    hist, edges = np.histogram(v, bins=bins)
    p = hist / hist.sum()
    centres = (edges[:-1] + edges[1:]) / 2
    w0 = np.cumsum(p)[:-1]                       # class 0 = bins 0..k, threshold at edges[k + 1]
    m = np.cumsum(p * centres)
    mu0 = m[:-1] / np.maximum(w0, 1e-300)
    mu1 = (m[-1] - m[:-1]) / np.maximum(1 - w0, 1e-300)
    between = w0 * (1 - w0) * (mu0 - mu1) ** 2
    # Empty bins between the modes make a plateau of equal maxima: take its middle, not its first edge.
    best = np.flatnonzero(between >= between.max() * (1 - 1e-9))
    return float((edges[1 + best[0]] + edges[1 + best[-1]]) / 2)


def finish_map(diff: np.ndarray, threshold: float, median: int, c: float, hit: np.ndarray | None = None) -> np.ndarray:
    """Threshold, median-filter, restrict to the mesh and scale by ``normalise_c(c)`` -> float32 HxW."""
    binary = np.asarray(diff) > threshold
    if median > 1:
        binary = median_mask(binary, int(median))
    if hit is not None:
        binary &= np.asarray(hit, bool)
    return (binary * encodings.normalise_c(c)).astype(np.float32)


def luminance(x: torch.Tensor) -> np.ndarray:
    """[B, 3, H, W] in [-1, 1] -> [B, H, W] Rec. 709 luminance in [0, 1] (float64)."""
    img = ((x.float().clamp(-1, 1) + 1) / 2).cpu().numpy().astype(np.float64)
    return imageops.luminance(np.moveaxis(img, 1, -1))


@torch.no_grad()
def relight_pairs(model, records: Sequence[Mapping[str, np.ndarray]], c_min: float, c_max: float, spec, *,
                  runtime=None, mean_matching: bool = True, device="cpu") -> np.ndarray:
    """Differences ``Y(relit at c_min) - Y(relit at c_max)`` (B, H, W) of records relit with their own light.

    A diffusion model inverts the B images in one batch and decodes the 2B targets in one batch."""
    names = model_inputs(model)
    x0 = torch.stack([image_to_tensor(a["image"]) for a in records]).to(device)
    targets = [retarget(a, names, np.asarray(a["light"]), c) for a in records for c in (c_max, c_min)]
    tcond = condition_tensors(model, targets, device)
    if isinstance(model, OnePassRelightable):  # one pass per record (its source condition is batch 1)
        out = [relight(model, x0[i:i + 1], condition_tensors(model, [a], device),
                       tuple(None if v is None else v[2 * i:2 * i + 2] for v in tcond), runtime=runtime)
               for i, a in enumerate(records)]
        relit = torch.cat(out)
    else:
        inv = invert_image(model, x0, condition_tensors(model, records, device), spec, runtime=runtime,
                           mean_matching=mean_matching)
        pairs = Inversion(inv.x_T.repeat_interleave(2, 0), inv.spec,
                          None if inv.offsets is None else inv.offsets.repeat_interleave(2, 1))
        relit = relight(model, x0, None, tcond, spec, runtime=runtime, inversion=pairs)
    errors.check_finite(relit.float().cpu().numpy(), "relit images of the difference method",
                        fix="the model produced NaN/Inf; try precision=fp32 or another checkpoint")
    y = luminance(relit)
    return y[1::2] - y[0::2]


@dataclass
class ShadowMapReport:
    name: str                 # shadow_map@<version>
    raw: str                  # shadow_map@diffraw-<hash>
    c_min: float
    c_max: float
    threshold: float
    relit: int                # records relit in this run (the rest were resumed)
    written: int
    seconds: float

    @property
    def images_per_second(self) -> float:
        return 2 * self.relit / self.seconds if self.seconds > 0 else float("nan")


def compute(model, store, spec, *, provenance: Mapping[str, Any], ids: Sequence[str] | None = None,
            split: str = "train", c_quantile: float = 0.01, threshold: str | float = "otsu", median: int = 3,
            batch_size: int = 8, version: str | None = None, runtime=None, mean_matching: bool = True,
            device="cpu", progress: bool = True) -> ShadowMapReport:
    """The whole difference pipeline over ``ids`` (default: every record); writes two derived versions."""
    if "shadow" not in model_inputs(model):
        raise errors.UserError(f"the difference method relights at two shadow strengths c, but this model consumes "
                               f"{model_inputs(model)} (no 'shadow'); give a DiFaReli checkpoint (model=difareli)")
    ids = list(ids) if ids is not None else store.ids()
    c_min, c_max = c_range(store, split, c_quantile)
    prov = {**dict(provenance), "c_min": c_min, "c_max": c_max, "split": split, "mean_matching": mean_matching,
            "c_quantile": float(c_quantile),
            "difference": "Y(relit at c_min) - Y(relit at c_max), own light"}
    raw = derived.declare(store, "shadow_map", derived.content_version("diffraw", prov),
                          {**prov, "stage": "raw difference"})
    # The global threshold depends on which records it is taken over: another record set is another version.
    chosen = "all" if set(ids) == set(store.ids()) else derived.content_version("ids", {"ids": sorted(ids)}, 12)
    version = version or derived.content_version("diff", {**prov, "threshold": threshold, "median": int(median),
                                                          "records": chosen})
    todo = derived.missing(store, raw, ids)
    needed = relight_reads(model_inputs(model))
    start = time.perf_counter()
    bar = tqdm(total=len(todo), desc="difference maps", disable=not progress)
    for i in range(0, len(todo), batch_size):
        chunk = todo[i:i + batch_size]
        recs = [dict(errors.check_record({k: np.asarray(v) for k, v in store.read(r, needed).items()}, r, store.root))
                for r in chunk]
        for rid, d in zip(chunk, relight_pairs(model, recs, c_min, c_max, spec, runtime=runtime,
                                               mean_matching=mean_matching, device=device)):
            derived.write(store, rid, raw, d.astype(np.float32), overwrite=True)
        bar.update(len(chunk))
        bar.set_postfix(img_s=f"{2 * (i + len(chunk)) / max(time.perf_counter() - start, 1e-9):.2f}")
    bar.close()
    seconds = time.perf_counter() - start
    hits = {r: (np.asarray(store.read(r, ["depth"])["depth"]) != 0) if store.available("depth") else None for r in ids}
    diffs = {r: np.asarray(store.read(r, [raw])[raw], dtype=np.float64) for r in ids}
    if threshold == "otsu":
        values = np.concatenate([(d[hits[r]] if hits[r] is not None else d).reshape(-1) for r, d in diffs.items()])
        thr, rule = otsu_threshold(values), "otsu over every difference value on the mesh of every record"
        if thr <= 0:  # a shadow darkens: a non-positive cut would call pixels that brightened with c shadow
            raise errors.UserError(
                f"Otsu's threshold of the differences is {thr:.4f} <= 0: this model does not darken the face as c "
                f"grows (step {provenance.get('global_step')}); train the DiFaReli longer or give threshold=<number>")
    else:
        thr, rule = float(threshold), "given"
    final = {**prov, "threshold": thr, "threshold_rule": rule, "median": int(median), "raw": raw, "records": chosen,
             "n_records": len(ids)}
    name = derived.declare(store, "shadow_map", version, final)
    written = 0
    for r in ids:
        c = encodings.shadow_logit(store.read(r, ["shadow"]))
        written += derived.write(store, r, name, finish_map(diffs[r], thr, median, c, hits[r]), overwrite=True)
    return ShadowMapReport(name, raw, c_min, c_max, thr, len(todo), written, seconds)
