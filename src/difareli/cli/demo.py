"""difareli-demo: the README's main job: a shipped checkpoint relights unseen faces (see ``difareli.jobs.demo``)."""

from __future__ import annotations

import time

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from difareli.diffusion.spec import check_sampler
from difareli import errors
from difareli.checkpoints import zoo
from difareli.cli import common
from difareli.jobs.demo import DemoResult, run_demo


def run(cfg: DictConfig) -> DemoResult:
    """Run the demo as configured; prints what it wrote and the benchmark table."""
    validate(cfg)
    if cfg.num_threads is not None:
        torch.set_num_threads(int(cfg.num_threads))
    start = time.perf_counter()
    res = run_demo(str(zoo.resolve(cfg.checkpoint)), cfg.out_dir, sampler=OmegaConf.to_container(cfg.sampler),
                   runtime=OmegaConf.to_container(cfg.runtime), subjects=int(cfg.subjects),
                   resolution=int(cfg.resolution), seed=int(cfg.seed), frames=int(cfg.frames), pairs=int(cfg.pairs),
                   rows=int(cfg.rows), photo=bool(cfg.photo), progress=bool(cfg.progress))
    if res.table is not None:
        print(f"Live check on {cfg.pairs} pairs per protocol of unseen subjects ({res.how}): "
              "too few pairs to rank the methods; read the ± standard errors")
        print(res.table.to_markdown())
    suite = zoo.suite()
    if suite:
        print(f"The shipped models' suite (the figures the README quotes):\n{suite}")
    elif card := card_benchmark(cfg.checkpoint):
        print(f"The model card's table for {cfg.checkpoint} (the figures the README quotes):\n{card}")
    for note in res.notes:
        print(note)
    for key, path in res.paths.items():
        print(f"{key}: {path}")
    print("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in res.seconds.items())
          + f"; total {time.perf_counter() - start:.1f}")
    return res


def card_benchmark(checkpoint: str) -> str | None:
    """The benchmark paragraph of a checkpoint's model card (shipped checkpoints have one), else None."""
    ckpt = errors.load_torch_file(zoo.resolve(checkpoint), "checkpoint")
    text = (ckpt.get("model_card") or {}).get("benchmark") if isinstance(ckpt, dict) else None
    return str(text) if text else None


def validate(cfg: DictConfig) -> None:
    """Config values, checked before any work."""
    check_sampler(cfg.sampler)
    zoo.resolve(cfg.checkpoint)
    for key, low in (("subjects", 10), ("resolution", 16), ("frames", 1), ("pairs", 1), ("rows", 1)):
        errors.check_int(cfg[key], key, low)
    errors.check_int(cfg.num_threads, "num_threads", 1, allow_none=True)
    errors.check_out_dir(cfg.out_dir)


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="demo")
@errors.cli_entry("demo")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
