"""Sampler speed/quality benchmark (SPEC 10): seconds per relight against error, per sampler and step count.

A *relight* is the whole per-image pipeline of :func:`difareli.relight.relighter.relight` at batch 1: Modulator on the
source condition, inversion, the mean-matching self-decode, Modulator on the target condition, and the decode,
run by a :class:`~difareli.runtime.core.Runtime` (device, precision, compile, CUDA graphs). ``time/seconds`` times these
network passes: encodings are read and checked at the relight door (:meth:`Relighter.source
<difareli.relight.relighter.Relighter.source>`), retargeted (:class:`~difareli.relight.targets.Targets`) and moved
to the device beforehand (:class:`Case`), the device is
synchronised around the timed region, and each sampler runs once untimed first. On store cases the retargeting is
timed too (``time/targets``: the target shadow map ray-marched on the source's depth and the shading re-rendered,
what every relight toward a new light pays on top), and ``time/end_to_end`` is the sum; with a student,
``speedup/end_to_end`` compares both sides with their target maps counted.

Quality is measured on the face mask with :mod:`difareli.evaluation.metrics` (MSE, DSSIM, images in [0, 1]) against two
references: the reference sampler's relight of the same input and target (DDIM-1000 by default: the
discretisation error alone) and, on SynthFaces, the ground truth: the same subject's record under the target
light. The target condition is what a user would have (the light fitted to the target image, an estimated or
policy c, encodings re-rendered on the source's geometry); ``oracle_target`` takes that record's own
light-dependent encodings (shading, shadow map, light, c), which SynthFaces renders exactly for the same geometry.

Untrained models (timing only) and their random inputs come from :mod:`difareli.perf.measure`.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from difareli.data import encodings
from difareli.evaluation import metrics
from difareli.utils import viz
from difareli.diffusion.relight import SamplerSpec
from difareli.data.inputs import Condition, condition_tensors, image_to_tensor
from difareli.perf.measure import random_condition
from difareli.relight.core import relight
from difareli.runtime.core import Runtime
from difareli.data.store import EncodingStore
from difareli.errors import MissingError, UserError
from difareli.relight.relighter import Relighter
from difareli.data.target_shadow import target_shadow_of
from difareli.relight.targets import Targets
from difareli.lighting.light_fit import LightFit
from difareli.utils.fileio import atomic_path

#: Error columns (present only when cases carry a reference or a ground truth).
ERROR_COLUMNS = ("ref/mse", "ref/dssim", "gt/mse", "gt/dssim")


@dataclass
class Case:
    """One benchmark relight with everything but the network passes prepared (tensors on the device)."""

    record: str
    target: str | None
    x0: Tensor                               # [1, 3, H, W] in [-1, 1]
    source: Condition                        # (spatial, nonspatial) of the input
    target_cond: Condition
    gt: Tensor | None = None                 # [1, 3, H, W] in [-1, 1]: the target record's image
    mask: Tensor | None = None               # [1, H, W] bool face mask
    inputs: str = ""                         # how the target condition was made (estimated or oracle inputs)
    target_seconds: float | None = None      # re-rendering the target's light-dependent encodings (shadow map)


def random_cases(n: int, model, resolution: int, device: str | torch.device = "cpu", seed: int = 0) -> list[Case]:
    """Random inputs of the model's input shapes for timing an untrained network (no references): per case an
    image, then the source and the target condition (:func:`difareli.perf.measure.random_condition`), one generator."""
    g = torch.Generator().manual_seed(seed)

    def case(i: int) -> Case:
        x0 = (torch.rand(1, 3, resolution, resolution, generator=g) * 2 - 1).to(device)
        source = random_condition(model, 1, resolution, device, generator=g)
        return Case(f"random{i}", None, x0, source, random_condition(model, 1, resolution, device, generator=g))

    return [case(i) for i in range(n)]


def same_subject_target(store: EncodingStore, record_id: str) -> str | None:
    """The first other record of the same subject (another light: SynthFaces' ground truth), or None."""
    subject = store.meta(record_id).get("subject")
    others = [r for r in store.ids(subject=subject) if r != record_id] if subject is not None else []
    return others[0] if others else None


def store_cases(store: EncodingStore, relighter: Relighter, records: Iterable[str] | None = None,
                limit: int | None = 2, *, oracle_target: bool = False) -> list[Case]:
    """Cases for ``records`` (default: the test split, else every record) under another light of the same subject,
    prepared through ``relighter``'s door (each source read and checked by :meth:`Relighter.source`, its target
    checked by :class:`~difareli.relight.targets.Targets` and :meth:`Relighter.check_inputs`), on its device.

    By default the target is what a user would have: the light fitted to the target record's image
    (:class:`~difareli.lighting.light_fit.LightFit`), the c of :func:`~difareli.data.target_shadow.target_shadow_of`,
    and the light-dependent encodings re-rendered on the source's geometry (shadow map ray-marched on its depth,
    toward the light's radiance peak). ``oracle_target`` takes the target record's stored light-dependent encodings
    instead. The ground truth is the target record's image and the mask the source's ``face_mask``; each case's
    ``inputs`` says which target was used.
    """
    ids = list(records) if records is not None else (store.ids(split="test") or store.ids())
    model, device, inputs = relighter.model, relighter.device, relighter.model_inputs
    rerender = encodings.light_dependent(inputs)
    fit = LightFit()
    cases = []
    for rid in ids:
        if limit is not None and len(cases) >= limit:
            break
        tid = same_subject_target(store, rid)
        if tid is None:
            continue
        source = relighter.source(store, rid)
        src = source.arrays
        if oracle_target:
            tgt = {**src, **store.read(tid, rerender)}
            note = "oracle target: the target record's stored light-dependent encodings"
            target_seconds = None
        else:
            c, how = target_shadow_of(store, tid)
            targets = Targets.of([fit.from_store(store, tid)], [c], f"target record {tid}")
            relighter.check_inputs(source, targets)
            # What a relight toward a new light pays besides the network: the target shadow map ray-marched on
            # the source's depth (and the shading re-rendered), timed so rows can report the end-to-end relight.
            clock = time.perf_counter()
            tgt = targets.retarget(src, inputs)[0]
            target_seconds = time.perf_counter() - clock
            note = (f"target light fitted to the target image (LightFit); {how}; "
                    f"re-rendered on the source: {', '.join(rerender) or 'nothing'}")
        # The source already holds its face mask where finding its key sun reads it (a shadow-map model).
        face = (src["face_mask"] if "face_mask" in src else
                store.read(rid, ["face_mask"])["face_mask"] if store.available("face_mask") else None)
        mask = None if face is None else torch.from_numpy(np.array(face))[None].bool().to(device)
        cases.append(Case(rid, tid, image_to_tensor(src["image"])[None].to(device),
                          condition_tensors(model, [src], device), condition_tensors(model, [tgt], device),
                          gt=image_to_tensor(store.read(tid, ["image"])["image"])[None].to(device), mask=mask,
                          inputs=note, target_seconds=target_seconds))
    if not cases:
        raise UserError(f"no record of {ids[:5]}{'...' if len(ids) > 5 else ''} in {store.root} has another record "
                        "of the same subject to relight toward (the benchmark's target and ground truth)")
    return cases


def timed_relight(model, case: Case, spec: SamplerSpec | None, runtime: Runtime, *, mean_matching: bool = True
                  ) -> tuple[Tensor, float]:
    """``(relit float32, seconds)`` of the whole per-image relight (both conditions, inversion, self-decode,
    decode) through the relighting core, the device synchronised before and after."""
    runtime.synchronize()
    with runtime.timed() as timer:
        out = relight(model, case.x0, case.source, case.target_cond, spec, runtime=runtime,
                      mean_matching=mean_matching)
    return out.float(), timer.seconds


def add_end_to_end(row: dict[str, Any], cases: Sequence[Case]) -> None:
    """``time/targets`` (median seconds re-rendering a case's target encodings: the shadow-map ray march) and
    ``time/end_to_end`` (network passes + that) on a row whose cases were made from a store's records."""
    secs = [c.target_seconds for c in cases]
    if secs and all(s is not None for s in secs):
        row["time/targets"] = float(np.median(secs))
        row["time/end_to_end"] = row["time/seconds"] + row["time/targets"]


def face_errors(pred: Tensor, ref: Tensor, mask: Tensor | None) -> dict[str, float]:
    """MSE and DSSIM of [-1, 1] images on the mask (whole image without one), in [0, 1] units."""
    p, r = metrics.from_signed(pred.float().clamp(-1, 1)), metrics.from_signed(ref.float().clamp(-1, 1))
    m = mask if mask is not None else torch.ones(p.shape[0], *p.shape[-2:], dtype=torch.bool, device=p.device)
    return {"mse": float(metrics.masked_mse(p, r, m).mean()), "dssim": float(metrics.dssim(p, r, m).mean())}


def spec_for(sampler_cfg: Mapping[str, Any], steps: int) -> SamplerSpec:
    """The configured sampler at ``steps`` steps."""
    return SamplerSpec.from_config({**dict(sampler_cfg), "steps": int(steps)})


def benchmark(model, cases: Sequence[Case], samplers: Mapping[str, Mapping[str, Any]], steps: Sequence[int], *,
              reference: tuple[str, int] | None = ("ddim", 1000), reference_config: Mapping[str, Any] | None = None,
              mean_matching: bool = True, runtime: Runtime | None = None, repeats: int = 1, warmup: bool = True,
              progress: bool = False) -> tuple[list[dict[str, Any]], dict]:
    """Time every ``samplers`` entry (name -> sampler config) at every step count on every case.

    ``reference`` = (sampler name, steps); its config is ``samplers[name]`` unless ``reference_config`` gives
    one (a reference sampler that is not benchmarked itself). Returns ``(rows, outputs)``: one row per (sampler, steps)
    with the mean seconds per relight, the network evaluations per relight (UNet passes) and, when available, mean
    errors against the reference relight and the ground truth; ``outputs[(sampler, steps)]`` holds the relit images (one
    per case).
    """
    if not cases:
        raise UserError("no cases to benchmark")
    if reference is not None and reference_config is None:
        if reference[0] not in samplers:
            raise MissingError(f"reference sampler {reference[0]!r} is not among the samplers {sorted(samplers)}")
        reference_config = samplers[reference[0]]
    runtime = runtime or Runtime(device=str(cases[0].x0.device))
    passes = 3 if mean_matching else 2
    if warmup:  # first calls pay for allocation, kernel selection, compilation and lazy initialisation
        for cfg in samplers.values():
            timed_relight(model, cases[0], spec_for(cfg, min(steps)), runtime, mean_matching=mean_matching)
    rows, outputs = [], {}
    jobs = [(name, n) for name in samplers for n in steps]
    for name, n in tqdm(jobs, desc="bench", disable=not progress):
        spec = spec_for(samplers[name], n)
        secs, outs = [], []
        for case in cases:
            for r in range(repeats):
                out, sec = timed_relight(model, case, spec, runtime, mean_matching=mean_matching)
                secs.append(sec)
            outs.append(out)
        outputs[(name, n)] = outs
        # The median resists other processes' bursts on a shared machine; the spread is reported beside it.
        rows.append({"sampler": name, "steps": n, "nfe": passes * n, "records": len(cases),
                     "time/seconds": float(np.median(secs)), "time/std": float(np.std(secs))})
        add_end_to_end(rows[-1], cases)
    ref_out = None
    if reference is not None:
        same = reference[0] in samplers and dict(samplers[reference[0]]) == dict(reference_config)
        ref_out = outputs.get(tuple(reference)) if same else None
        if ref_out is None:
            spec = spec_for(reference_config, reference[1])
            ref_out = [timed_relight(model, c, spec, runtime, mean_matching=mean_matching)[0] for c in
                       tqdm(cases, desc=f"reference {reference[0]}-{reference[1]}", disable=not progress)]
        outputs["reference"] = ref_out
    for row in rows:
        outs = outputs[(row["sampler"], row["steps"])]
        for key, refs in (("ref", ref_out), ("gt", [c.gt for c in cases])):
            if refs is None or any(r is None for r in refs):
                continue
            errs = [face_errors(o, r, c.mask) for o, r, c in zip(outs, refs, cases)]
            for m in ("mse", "dssim"):
                row[f"{key}/{m}"] = float(np.mean([e[m] for e in errs]))
    return rows, outputs


def add_one_pass(rows: list[dict[str, Any]], outputs: dict, model, cases: Sequence[Case], *, name: str = "student",
                 runtime: Runtime | None = None, repeats: int = 1, warmup: bool = True) -> dict[str, Any]:
    """Time a one-pass model (the student) on ``cases`` (the same records and targets as the teacher's rows,
    conditions prepared for this model) in the same run: append its row (1 network pass, errors against the
    teacher's reference relights and the ground truth) and give every teacher row its ``speedup`` (teacher
    seconds / student seconds per relight). Returns the student's row."""
    runtime = runtime or Runtime(device=str(cases[0].x0.device))
    if warmup:
        timed_relight(model, cases[0], None, runtime)
    secs, outs = [], []
    for case in cases:
        for _ in range(repeats):
            out, sec = timed_relight(model, case, None, runtime)
            secs.append(sec)
        outs.append(out)
    row = {"sampler": name, "steps": 1, "nfe": 1, "records": len(cases), "time/seconds": float(np.median(secs)),
           "time/std": float(np.std(secs)), "speedup": 1.0}
    add_end_to_end(row, cases)
    for key, refs in (("ref", outputs.get("reference")), ("gt", [c.gt for c in cases])):
        if refs is None or any(r is None for r in refs):
            continue
        errs = [face_errors(o, r, c.mask) for o, r, c in zip(outs, refs, cases)]
        for m in ("mse", "dssim"):
            row[f"{key}/{m}"] = float(np.mean([e[m] for e in errs]))
    for r in rows:
        r["speedup"] = r["time/seconds"] / row["time/seconds"]
        if "time/end_to_end" in r and "time/end_to_end" in row:  # both sides counting their target shadow maps
            r["speedup/end_to_end"] = r["time/end_to_end"] / row["time/end_to_end"]
    if "time/end_to_end" in row:
        row["speedup/end_to_end"] = 1.0
    rows.append(row)
    outputs[(name, 1)] = outs
    return row


# ------------------------------------------------------------------------------------------ reporting
def columns(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    keys = ["sampler", "steps", "nfe", "records", "time/seconds", "time/std"]
    optional = ("time/targets", "time/end_to_end", *ERROR_COLUMNS, "speedup", "speedup/end_to_end")
    return keys + [c for c in optional if any(c in r for r in rows)]


def write_csv(rows: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns(rows), extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return path


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """A plain-text table, one line per (sampler, steps)."""
    cols = columns(rows)
    widths = {c: max(len(c), 14 if c == "sampler" else 9) for c in cols}

    def cell(c, v):
        if isinstance(v, str):
            return f"{v:<{widths[c]}}"
        if isinstance(v, int):
            return f"{v:>{widths[c]}d}"
        return f"{v:>{widths[c]}.4g}" if v is not None and math.isfinite(v) else f"{'-':>{widths[c]}}"

    head = "  ".join(f"{c:<{widths[c]}}" if c == "sampler" else f"{c:>{widths[c]}}" for c in cols)
    return "\n".join([head] + ["  ".join(cell(c, r.get(c)) for c in cols) for r in rows])


def pareto_plot(rows: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Seconds per relight against each error column (log-log, one line per sampler, points labelled by steps);
    timing-only rows plot seconds against steps. Zero errors (the reference against itself) cannot sit on a
    log axis and are left out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    errs = [c for c in ERROR_COLUMNS if any(c in r for r in rows)]
    panels = errs or [None]
    ncol = min(2, len(panels))
    nrow = math.ceil(len(panels) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(5.5 * ncol, 4.2 * nrow), squeeze=False)
    samplers = list(dict.fromkeys(r["sampler"] for r in rows))
    for ax, col in zip(axes.flat, panels):
        for name in samplers:
            if col is None:
                pts = sorted((r["steps"], r["time/seconds"], r["steps"]) for r in rows if r["sampler"] == name)
            else:
                pts = sorted((r["time/seconds"], r[col], r["steps"]) for r in rows
                             if r["sampler"] == name and col in r and r[col] > 0 and r["time/seconds"] > 0)
            if not pts:
                continue
            x, y, n = zip(*pts)
            (line,) = ax.plot(x, y, "o-", label=name)
            for xi, yi, ni in zip(x, y, n):
                ax.annotate(str(ni), (xi, yi), fontsize=7, color=line.get_color(), xytext=(3, 3),
                            textcoords="offset points")
        ax.set(xscale="log", yscale="log")
        if col is None:
            ax.set(xlabel="steps", ylabel="seconds per relight", title="timing only (untrained network)")
        else:
            ax.set(xlabel="seconds per relight (network passes)", ylabel=col, title=f"{col} vs time")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def comparison_grid(cases: Sequence[Case], outputs: Mapping, steps: Sequence[int], path: str | Path,
                    case_index: int = 0) -> Path:
    """One image of one case: a first row (input, ground truth, reference), then per sampler its relights
    at each step count, left to right."""
    c = cases[case_index]
    head = [viz.to_uint8(c.x0[0])]
    head += [viz.to_uint8(c.gt[0])] if c.gt is not None else []
    head += [viz.to_uint8(outputs["reference"][case_index][0].clamp(-1, 1))] if "reference" in outputs else []
    samplers = list(dict.fromkeys(k[0] for k in outputs if k != "reference"))
    def row(s):
        keys = [(s, n) for n in steps if (s, n) in outputs] or [(s, 1)]  # a one-pass model: its one relight
        return [viz.to_uint8(outputs[k][case_index][0].clamp(-1, 1)) for k in keys]

    rows = [head] + [row(s) for s in samplers]
    k = max(1, 128 // head[0].shape[0])  # small test resolutions: enlarge (nearest) so faces stay visible
    rows = [[im.repeat(k, 0).repeat(k, 1) for im in row] for row in rows]
    return viz.save_png(viz.grid(rows), path)
