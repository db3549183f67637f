"""difareli-demo: the README's main job: a shipped checkpoint relights unseen faces (see ``difareli.jobs.demo``)."""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from difareli import errors
from difareli.checkpoints import zoo
from difareli.checkpoints.format import load_torch_file
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
    print(answer(cfg, res))
    return res


def answer(cfg: DictConfig, res: DemoResult) -> str:
    """The block the demo ends with: what ran, the pictures to open, and the live check in one line per
    protocol (the tables above are the detail)."""
    lines = ["", "== difareli-demo: the answer ==",
             f"model: {cfg.checkpoint} ({res.how}), on SynthFaces subjects it never saw (seed {cfg.seed})"]
    look = {"comparison": "input | relit | ground truth", "video": "the light turning 360 degrees",
            "sheet": "the rotation's frames with their light angle", "photo": "the astronaut: input | 4 new lights"}
    for key, what in look.items():
        if key in res.paths:
            path = Path(res.paths[key])
            size = f", {path.stat().st_size / 1024:.0f} kB" if key == "video" and path.is_file() else ""
            lines.append(f"open: {path} ({what}{size})")
    table = res.table
    baselines = ("identity", "lambertian")
    if table is not None and any(m not in baselines for m in table.methods):
        model = next(m for m in table.methods if m not in baselines)
        for proto in table.protocols:
            got = {m: table.cells[(m, proto)]["dssim"] for m in table.methods if (m, proto) in table.cells}
            best = min(got, key=lambda m: got[m].mean)
            lines.append(f"DSSIM, {proto}-subject pairs (lower is better, n={got[model].n}): "
                         + ", ".join(f"{'model' if m == model else m} {v.mean:.3f} ± {v.se:.3f}"
                                     for m, v in got.items())
                         + f"; best: {'the model' if best == model else best}")
    lines.append("the shipped suite above (100 pairs per protocol) is the measured ranking; these few live pairs "
                 "only show the model runs here")
    return "\n".join(lines)


def card_benchmark(checkpoint: str) -> str | None:
    """The benchmark paragraph of a checkpoint's model card (shipped checkpoints have one), else None."""
    ckpt = load_torch_file(zoo.resolve(checkpoint), "checkpoint")
    text = (ckpt.get("model_card") or {}).get("benchmark") if isinstance(ckpt, dict) else None
    return str(text) if text else None


def validate(cfg: DictConfig) -> None:
    """Config values, checked before any work."""
    common.check_relighting(cfg)  # before the store is made and the checkpoint read
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
