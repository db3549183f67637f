"""difareli-bench-samplers: seconds per relight vs error for each sampler x step count (SPEC 10).

Writes ``bench_samplers.csv``, ``bench_samplers.png`` (the Pareto plot) and, with a trained checkpoint,
``bench_samplers_grid.png`` (one record relit by every sampler at every step count) into the run dir.
"""

from __future__ import annotations

from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from difareli import errors
from difareli.perf import measure as perf
from difareli.perf import samplers as speed
from difareli.checkpoints import loading
from difareli.cli import common
from difareli.relight.relightable import OnePassRelightable
from difareli.relight.relighter import Relighter
from difareli.runtime.core import Runtime
from difareli.utils.fileio import write_text_atomic
from difareli.data.store import EncodingStore


def run(cfg: DictConfig) -> dict:
    """Benchmark as configured; returns ``{"rows", "paths"}``."""
    for i, n in enumerate(cfg.steps):
        errors.check_int(n, f"steps[{i}]", 1)
    errors.check_int(cfg.limit, "limit", 1, allow_none=True)
    errors.check_int(cfg.repeats, "repeats", 1)
    errors.check_int(cfg.student_repeats, "student_repeats", 1)
    errors.check_out_dir(cfg.out_dir)
    if cfg.checkpoint is not None:
        loading.resolve(cfg.checkpoint, "checkpoint")
    runtime = Runtime.from_config(cfg.runtime)
    device = runtime.torch_device
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    configured = OmegaConf.to_container(cfg.samplers, resolve=True)
    names = list(cfg.names) if cfg.names is not None else list(configured)
    unknown = [n for n in names if n not in configured]
    if unknown:
        raise errors.MissingError(f"names {unknown} are not configured under samplers ({sorted(configured)}); add one "
                                  "with +sampler@samplers.<name>=<conf/sampler file>")
    samplers = {n: configured[n] for n in names}
    steps = sorted({int(n) for n in cfg.steps})
    if cfg.checkpoint is not None:
        if cfg.store is None:
            raise errors.UserError("store=... is required with a checkpoint (the records to relight)")
        relighter = Relighter(cfg.checkpoint, runtime=runtime)  # the cases are read and checked at its door
        model = relighter.model
        if isinstance(model, OnePassRelightable):  # every sampler row would time the same single pass
            raise errors.UserError(f"checkpoint={cfg.checkpoint} is a one-pass student: it has no sampler or step "
                                   "count to sweep; time it beside its teacher: checkpoint=<teacher> "
                                   f"student={cfg.checkpoint}")
        cases = speed.store_cases(EncodingStore.open(cfg.store), relighter,
                                  records=list(cfg.records) if cfg.records is not None else None, limit=cfg.limit,
                                  oracle_target=errors.check_bool(cfg.get("oracle_target", False), "oracle_target"))
        reference = (cfg.reference.sampler, int(cfg.reference.steps)) if cfg.reference is not None else None
        if reference is not None and reference[0] not in configured:
            raise errors.MissingError(f"reference.sampler={reference[0]!r} is not configured under samplers "
                                      f"({sorted(configured)})")
        what = f"{cfg.checkpoint} on {len(cases)} record(s) of {cfg.store} ({cases[0].inputs})"
    else:
        model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
        model, res = perf.untrained_model(model_cfg, model_cfg.pop("preset"), cfg.resolution, device, seed=cfg.seed)
        cases = speed.random_cases(cfg.limit or 1, model, res, device, seed=cfg.seed)
        reference = None  # an untrained network's relights say nothing about quality
        what = f"untrained {cfg.model.preset} {cfg.model.name} ({res} px), timing only"
    print(f"bench-samplers: {what}, device {device}, {runtime.precision}"
          f"{', compiled' if runtime.compile else ''}{', CUDA graphs' if runtime.cuda_graphs else ''}")
    # The student and its cases are prepared before the teacher's rows, so that a bad student fails in seconds.
    student, student_cases = _student(cfg, cases, runtime) if cfg.get("student") is not None else (None, None)
    rows, outputs = speed.benchmark(model, cases, samplers, steps, reference=reference,
                                    reference_config=configured[reference[0]] if reference else None,
                                    mean_matching=cfg.mean_matching, runtime=runtime, repeats=cfg.repeats,
                                    warmup=cfg.warmup, progress=cfg.progress)
    if student is not None:  # the one-pass student timed in this run: one point + every ratio
        speed.add_one_pass(rows, outputs, student, student_cases, name=student.hparams.get("name", "student"),
                           runtime=runtime, repeats=max(cfg.repeats, cfg.student_repeats), warmup=cfg.warmup)
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "inputs.txt", what + "\n")  # which inputs (estimated or oracle) the table used
    paths = {"csv": speed.write_csv(rows, out / "bench_samplers.csv"),
             "plot": speed.pareto_plot(rows, out / "bench_samplers.png")}
    if cfg.checkpoint is not None:
        paths["grid"] = speed.comparison_grid(cases, outputs, steps, out / "bench_samplers_grid.png")
    print(speed.format_table(rows))
    for k, p in paths.items():
        print(f"{k}: {p}")
    return {"rows": rows, "paths": paths}


def _student(cfg: DictConfig, cases: list, runtime: Runtime) -> tuple:
    """The student (a checkpoint, or ``untrained``: conf/model/student at the teacher's preset and resolution)
    and its cases: the teacher's records and targets, conditions prepared for the student at its own door."""
    device = runtime.torch_device
    if cfg.student == "untrained":
        model_cfg = OmegaConf.to_container(cfg.student_model, resolve=True)
        preset = cfg.model.preset if cfg.checkpoint is None else model_cfg.pop("preset")
        model_cfg.pop("preset", None)
        student, res = perf.untrained_model(model_cfg, preset, cases[0].x0.shape[-1], device, seed=cfg.seed)
        if cfg.checkpoint is None:
            return student, speed.random_cases(len(cases), student, res, device, seed=cfg.seed)
        checkpoint = loading.LoadedCheckpoint.of_module(student)
    else:
        if cfg.checkpoint is None:
            raise errors.UserError("student=<checkpoint> is timed against a teacher checkpoint: give checkpoint=... "
                                   "and store=..., or student=untrained for timing only")
        checkpoint = loading.resolve(cfg.student, "student")
    relighter = Relighter(checkpoint, runtime=runtime)
    if not isinstance(relighter.model, OnePassRelightable):
        raise errors.UserError(f"student={cfg.student} is not a one-pass model; give a model=student checkpoint")
    return relighter.model, speed.store_cases(EncodingStore.open(cfg.store), relighter,
                                              records=[c.record for c in cases], limit=None)


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="bench_samplers")
@errors.cli_entry("bench-samplers")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
