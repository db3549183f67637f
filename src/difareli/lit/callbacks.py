"""Callbacks that write images people would rather see than read."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import lightning as L
import torch

from difareli import viz


class ReconstructionGrid(L.Callback):
    """At each validation, noise ``num_images`` validation images to several ``timesteps`` and write a grid of
    one-step x0 reconstructions (rows: images; columns: input, then x_t / x0-hat pairs per t).

    Runs on the weights being validated (the EMA weights when the EMA callback is on).
    """

    def __init__(self, num_images: int = 8, timesteps: Sequence[int] = (100, 300, 600, 900), seed: int = 0):
        self.num_images, self.timesteps, self.seed = num_images, list(timesteps), seed

    @torch.no_grad()
    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero or trainer.datamodule is None:
            return
        ds = trainer.datamodule.val_set
        n = min(self.num_images, len(ds))
        batch = [ds[i] for i in range(n)]
        dev = pl_module.device
        x0 = torch.stack([b["image"] for b in batch]).to(dev)
        spatial = torch.stack([b["spatial"] for b in batch]).to(dev)
        nonspatial = torch.stack([b["nonspatial"] for b in batch]).to(dev)
        cond = pl_module.condition(spatial, nonspatial)
        g = torch.Generator(device=dev).manual_seed(self.seed)
        noise = torch.randn(x0.shape, generator=g, device=dev)
        cols = [[viz.to_uint8(x) for x in x0]]
        for t_val in self.timesteps:
            t = torch.full((n,), t_val, device=dev, dtype=torch.long)
            x_t = pl_module.schedule.q_sample(x0, t, noise)
            cols.append([viz.to_uint8(x.clamp(-1, 1)) for x in x_t])
            cols.append([viz.to_uint8(x) for x in pl_module.predict_x0(x_t, t, cond)])
        rows = [[c[i] for c in cols] for i in range(n)]
        path = Path(trainer.default_root_dir) / "grids" / f"reconstruction_step{trainer.global_step:07d}.png"
        viz.save_png(viz.grid(rows), path)
