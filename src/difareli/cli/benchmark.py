"""difareli-benchmark: one relighting method on the SynthFaces protocols -> relit images, per-image CSV, tables."""

from __future__ import annotations

from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from difareli.baselines import build_method, light_fit_from_config
from difareli.benchmark import BenchmarkResult, run_benchmark
from difareli.cli import common
from difareli.store import EncodingStore


def run(cfg: DictConfig) -> BenchmarkResult:
    """Benchmark the configured method; prints and returns the summary."""
    if cfg.num_threads:
        torch.set_num_threads(int(cfg.num_threads))
    store = EncodingStore.open(cfg.store)
    estimator = light_fit_from_config(OmegaConf.to_container(cfg.light_fit, resolve=True))
    method_cfg = OmegaConf.to_container(cfg.method, resolve=True)
    # Methods that use the light get a marked name under ground-truth lights, so merged tables keep both.
    suffix = "+gt-light" if cfg.oracle_light and method_cfg["kind"] in ("lambertian", "diffusion") else ""
    method = build_method(method_cfg, sampler=OmegaConf.to_container(cfg.sampler, resolve=True),
                          runtime=OmegaConf.to_container(cfg.runtime, resolve=True), estimator=None if cfg.oracle_light else estimator, name_suffix=suffix)
    limit = int(cfg.limit) if cfg.limit is not None else None
    result = run_benchmark(store, method, list(cfg.protocols), Path(cfg.out_dir), limit=limit,
                           oracle_light=bool(cfg.oracle_light), estimator=estimator, grid_pairs=int(cfg.grid_pairs),
                           save_images=bool(cfg.save_images), progress=bool(cfg.progress))
    print(result.paths["summary_md"].read_text())
    print(f"per-image scores: {result.paths['per_image']}")
    return result


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="benchmark")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
