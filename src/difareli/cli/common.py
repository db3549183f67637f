"""Small helpers shared by the thin Hydra entry points."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

#: The repository's conf/ folder (editable install). Absolute: Hydra resolves a relative config_path against
#: the calling *module* when started from a console script, which would look for a `conf` package.
CONFIG_PATH = str(Path(__file__).resolve().parents[3] / "conf")


def instantiate_group(group: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` entry of a config group (callbacks, loggers); ``None`` -> ``[]``."""
    if not group:
        return []
    return [hydra.utils.instantiate(c) for c in group.values() if isinstance(c, DictConfig) and "_target_" in c]


def log_hyperparameters(trainer, cfg: DictConfig) -> None:
    """Send the resolved config to every logger (Hydra also saves it under <run>/.hydra/config.yaml)."""
    flat = OmegaConf.to_container(cfg, resolve=True)
    for logger in trainer.loggers:
        logger.log_hyperparams(flat)


def metric_value(metrics: dict, name: str | None) -> float | None:
    """The optimized metric for Hydra sweepers, or None when absent (e.g. fast_dev_run)."""
    if not name or name not in metrics:
        return None
    return float(metrics[name])


@torch.no_grad()
def write_sample_grid(model, datamodule, sampler_cfg: DictConfig, out_dir: str | Path, n: int = 8) -> Path:
    """Generate ``n`` images from pure noise under validation conditions with the configured sampler, and
    write ``sample_grid.png`` (top row: the real images, bottom row: samples under their encodings)."""
    from difareli import viz
    from difareli.diffusion import samplers

    ds = datamodule.val_set
    n = min(n, len(ds))
    items = [ds[i] for i in range(n)]
    model.eval()
    dev = model.device
    spatial = torch.stack([b["spatial"] for b in items]).to(dev)
    nonspatial = torch.stack([b["nonspatial"] for b in items]).to(dev)
    cond = model.condition(spatial, nonspatial)
    g = torch.Generator(device=dev).manual_seed(0)
    x_T = torch.randn((n, *items[0]["image"].shape), generator=g, device=dev)
    grid_t = model.schedule.time_grid(int(sampler_cfg.steps), kind=sampler_cfg.grid, direction="generate")
    fn = samplers.get_sampler(sampler_cfg.name)
    x0 = fn(model.denoiser(cond), x_T, grid_t, model.schedule, clip_x0=bool(sampler_cfg.clip_x0_generate),
            **samplers.sampler_options(sampler_cfg))
    rows = [[viz.to_uint8(b["image"]) for b in items], [viz.to_uint8(x.clamp(-1, 1)) for x in x0]]
    return viz.save_png(viz.grid(rows), Path(out_dir) / "sample_grid.png")
