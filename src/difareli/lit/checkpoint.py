"""Loading trained models from checkpoints, for notebooks and CLIs: only the package and the file."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from difareli.errors import load_torch_file
from difareli.lit.diffusion import DiffusionModule


@dataclass
class LoadedCheckpoint:
    """A model ready for inference plus what it was trained with."""

    model: DiffusionModule
    config: dict[str, Any]
    stats: dict[str, torch.Tensor]
    global_step: int


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> LoadedCheckpoint:
    """Load a checkpoint with ``torch.load(weights_only=True)``.

    The weights are the EMA weights when training used the EMA callback (Lightning stores the average in
    ``state_dict``); the config is the model's plain hyperparameters; stats are the non-spatial
    normalisation statistics of the training split.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist (difareli-train writes <run>/checkpoints/last.ckpt)")
    ckpt = load_torch_file(path, "checkpoint", map_location)  # torch.load(weights_only=True), errors name the file
    if "hyper_parameters" not in ckpt or "state_dict" not in ckpt:
        raise ValueError(f"{path} is not a difareli Lightning checkpoint (no hyper_parameters/state_dict)")
    config = dict(ckpt["hyper_parameters"])
    config.pop("compile", None)  # inference never compiles implicitly
    model = DiffusionModule(**config)
    model.load_state_dict(ckpt["state_dict"])
    model.eval().requires_grad_(False)
    model.to(map_location)
    stats = {"mean": model.ns_mean.clone(), "std": model.ns_std.clone()}
    return LoadedCheckpoint(model=model, config=config, stats=stats, global_step=int(ckpt.get("global_step", 0)))
