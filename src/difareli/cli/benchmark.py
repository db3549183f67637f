"""difareli-benchmark: one relighting method on a store's protocols (SynthFaces, or Multi-PIE
from difareli-multipie)
-> relit images, per-image CSV, tables; scored under ``metrics.rule`` (paper | composite,
difareli.evaluation.metrics). The command's door: each config value is checked here, once, before any work, and
one typed job goes down (a :class:`~difareli.evaluation.benchmark.BenchmarkJob`, or for ``rescore=`` a
:class:`~difareli.evaluation.rescore.Rescore`)."""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from difareli import errors
from difareli.checkpoints import loading
from difareli.configs import CONFIG_DIR
from difareli.data import shard as sharding
from difareli.evaluation.baselines import build_method
from difareli.lighting.light_fit import LightFit, light_fit_from_config
from difareli.evaluation.benchmark import BenchmarkJob
from difareli.evaluation.rescore import Rescore
from difareli.evaluation.result import BenchmarkResult
from difareli.evaluation.scoring import DEFAULT_MASK, Scoring
from difareli.cli import common
from difareli.lit import logging as lit_logging
from difareli.data.store import EncodingStore

#: The config keys that define a benchmark job; shards of one job differ only by ``shard``.
SHARD_JOB_KEYS = ("store", "method", "sampler", "protocols", "limit", "oracle_light", "oracle_shadow",
                  "light_fit", "versions", "metrics", "score_mask", "target_sun")


def run(cfg: DictConfig) -> BenchmarkResult:
    """Benchmark the configured method (``rescore=``: :func:`rescore_run` instead); prints and returns the summary."""
    if cfg.get("rescore"):
        return rescore_run(cfg)
    job = benchmark_job(cfg)
    result = job.run()
    if job.shard is not None:  # what difareli-table checks before merging shards: same job, every shard once
        sharding.write_marker(job.out_dir, job.shard, shard_job(cfg))
    if cfg.get("logger"):  # the summary table and comparison grids to wandb / TensorBoard (logger=many_loggers)
        lit_logging.log_benchmark(cfg, result)
    print(result.paths["summary_md"].read_text())
    print(f"per-image scores: {result.paths['per_image']}")
    return result


def rescore_run(cfg: DictConfig) -> BenchmarkResult:
    """``rescore=<run dir>``: the saved relit images of a finished run scored again as the config says (no
    relighting); prints and returns the summary."""
    store, scoring, estimator = checked(cfg)
    result = Rescore(store, Path(cfg.rescore), Path(cfg.out_dir), scoring, estimator).run()
    print(result.paths["summary_md"].read_text())
    return result


def checked(cfg: DictConfig) -> tuple[EncodingStore, Scoring, LightFit]:
    """The config, each value checked before any work (:func:`validate`), and what every run of the command reads
    from it: the store, how pairs are scored and the light fit."""
    with_checkpoint(cfg)
    validate(cfg)
    store = EncodingStore.open(cfg.store).use_versions(cfg.get("versions"))
    # The rule, the score mask and the target sun, checked once, before the method (and its checkpoint) is built.
    scoring = Scoring.of(store, OmegaConf.select(cfg, "metrics.rule", default=None), cfg.get("score_mask"),
                         cfg.get("target_sun", "shadows"))
    return store, scoring, light_fit_from_config(OmegaConf.to_container(cfg.light_fit, resolve=True))


def benchmark_job(cfg: DictConfig) -> BenchmarkJob:
    """The benchmark the config asks for, every value checked (:func:`checked`, the shard) before its method (and
    its checkpoint) is built."""
    store, scoring, estimator = checked(cfg)
    try:
        spec = sharding.parse(cfg.get("shard"))  # before any work: a bad value fails in one line
    except ValueError as e:
        raise errors.UserError(f"shard={cfg.get('shard')!r}: {e}") from None
    if cfg.num_threads:
        torch.set_num_threads(int(cfg.num_threads))
    method = build_method(OmegaConf.to_container(cfg.method, resolve=True),
                          sampler=OmegaConf.to_container(cfg.sampler, resolve=True),
                          runtime=OmegaConf.to_container(cfg.runtime, resolve=True),
                          estimator=None if cfg.oracle_light else estimator)
    # Methods that use the light get a marked name under ground-truth lights, so merged tables keep both.
    if cfg.oracle_light and method.needs_light:
        method.name += "+gt-light"
    elif cfg.get("oracle_shadow") and method.needs_light:
        method.name += "+gt-c"
    return BenchmarkJob(store, method, tuple(cfg.protocols), Path(cfg.out_dir), scoring,
                        limit=None if cfg.limit is None else int(cfg.limit), oracle_light=bool(cfg.oracle_light),
                        oracle_shadow=bool(cfg.get("oracle_shadow", False)), estimator=estimator,
                        grid_pairs=int(cfg.grid_pairs), save_images=bool(cfg.save_images),
                        progress=bool(cfg.progress), shard=spec)


def shard_job(cfg: DictConfig) -> dict:
    """What a shard's marker says of its job (:data:`SHARD_JOB_KEYS`, the store's resolved path): what
    difareli-table compares before merging shards."""
    job = {k: OmegaConf.to_container(cfg[k], resolve=True) if OmegaConf.is_config(cfg[k]) else cfg[k]
           for k in SHARD_JOB_KEYS if k in cfg}
    if job.get("score_mask") == DEFAULT_MASK:  # shards of runs from before the option stay mergeable
        job.pop("score_mask")
    return {**job, "store": str(Path(cfg.store).resolve())}


def with_checkpoint(cfg: DictConfig) -> None:
    """``checkpoint=<name or file>``: the diffusion method's ``method.checkpoint``, with ``method=diffusion`` implied
    (in place of the default method) or said; another method said beside it, or two checkpoints, is one line."""
    ckpt = cfg.get("checkpoint")
    if ckpt is None:
        return
    said = [o for o in _overrides() if o.split("=", 1)[0].lstrip("+~") == "method"]
    if not str(cfg.method.get("_target_", "")).endswith(".DiffusionMethod"):
        if said:
            raise errors.UserError(f"checkpoint={ckpt} relights with method=diffusion, and {said[0]} was given too; "
                                   "drop one of them")
        with open_dict(cfg):
            cfg.method = OmegaConf.load(Path(CONFIG_DIR) / "method" / "diffusion.yaml")
    if cfg.method.get("checkpoint") not in (None, "???", ckpt):
        raise errors.UserError(f"checkpoint={ckpt} and method.checkpoint={cfg.method.checkpoint} name two "
                               "checkpoints; give one of them")
    with open_dict(cfg):
        cfg.method.checkpoint = ckpt


def _overrides() -> list[str]:
    """The command line's overrides (none outside a Hydra run)."""
    try:
        return list(HydraConfig.get().overrides.task)
    except ValueError:
        return []


def validate(cfg: DictConfig) -> None:
    """Config values, checked before any work: a bad value is a UserError naming the key."""
    errors.check_int(cfg.limit, "limit", 1, allow_none=True)
    errors.check_int(cfg.grid_pairs, "grid_pairs", 0)
    errors.check_int(cfg.num_threads, "num_threads", 1, allow_none=True)
    for key in ("oracle_light", "oracle_shadow", "save_images", "progress"):  # oracle_light=no is no "true"
        errors.check_bool(cfg.get(key, False), key)  # a config without a key reads false, as benchmark_job does
    errors.check_out_dir(cfg.out_dir)
    if "checkpoint" in cfg.method:  # a trained model (the diffusion method): its sampler, runtime and file
        common.check_relighting(cfg)
        loading.resolve(cfg.method.get("checkpoint") or "", "method.checkpoint")


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="benchmark")
@errors.cli_entry("benchmark")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
