"""Loading trained models from checkpoints, for notebooks and CLIs: only the package and the file.

A checkpoint records the module class that wrote it (``difareli_module``) and its format (``difareli_format``);
:func:`load_checkpoint` imports that class (only from the ``difareli.`` namespace) and builds it from the plain
hyperparameters. Checkpoints written before format 2 (flat ``spatial_type`` / ``modulate_skips`` / ``lr`` /
``weight_decay``, statistics in ``state_dict`` buffers) are translated by :func:`upgrade_checkpoint`.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch

from difareli import zoo
from difareli.errors import load_torch_file
from difareli.lit.diffusion import FORMAT_KEY, FORMAT_VERSION, MODULE_KEY

#: The class of checkpoints that predate ``difareli_module`` (all of them were DiffusionModules).
LEGACY_MODULE = "difareli.lit.diffusion.DiffusionModule"
#: Modules a checkpoint may name: the package's own namespace only (a checkpoint is data, not code).
ALLOWED_PREFIX = "difareli."


@dataclass
class LoadedCheckpoint:
    """A model ready for inference plus what it was trained with."""

    model: L.LightningModule
    config: dict[str, Any]
    stats: dict[str, torch.Tensor]
    global_step: int


def upgrade_checkpoint(ckpt: dict[str, Any]) -> dict[str, Any]:
    """Translate a pre-format-2 checkpoint dict in place (and return it); newer ones pass unchanged.

    ``spatial_type`` + ``modulate_skips`` -> ``spatial: {type, modulate_skips}``; ``lr`` + ``weight_decay`` ->
    ``optimizer`` (AdamW, as trained); ``ns_mean`` / ``ns_std`` buffers -> ``nonspatial_stats`` lists;
    ``adagn_out_silu`` -> ``False`` (those networks had no output SiLU).
    """
    if ckpt.get(FORMAT_KEY, 1) >= FORMAT_VERSION:
        return ckpt
    hp = dict(ckpt["hyper_parameters"])
    kind, skips = hp.pop("spatial_type", "modulator"), hp.pop("modulate_skips", False)
    if kind in (None, "none") or not hp.get("spatial_inputs"):
        hp["spatial"] = None
    else:  # modulate_skips was the Modulator's option; no other component took one
        hp["spatial"] = {"type": kind, **({"modulate_skips": bool(skips)} if kind == "modulator" else {})}
    hp["optimizer"] = {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": float(hp.pop("lr", 1e-4)),
                       "weight_decay": float(hp.pop("weight_decay", 0.0))}
    hp.setdefault("scheduler", None)
    hp.setdefault("adagn_out_silu", bool(dict(hp.get("net_overrides") or {}).get("adagn_out_silu", False)))
    stats = None
    for key in ("state_dict", "current_model_state"):  # the EMA callback keeps the raw weights in the latter
        if key in ckpt:
            sd = dict(ckpt[key])
            mean, std = sd.pop("ns_mean", None), sd.pop("ns_std", None)
            ckpt[key] = sd
            if key == "state_dict" and mean is not None:
                stats = {"mean": mean.float().tolist(), "std": std.float().tolist()}
    hp["nonspatial_stats"] = stats
    ckpt["hyper_parameters"] = hp
    ckpt.setdefault(MODULE_KEY, LEGACY_MODULE)
    ckpt[FORMAT_KEY] = FORMAT_VERSION
    return ckpt


def module_class(path: str) -> type[L.LightningModule]:
    """Import the LightningModule class named ``package.module.Class`` (``difareli.`` namespace only)."""
    if not isinstance(path, str) or not path.startswith(ALLOWED_PREFIX) or "." not in path[len(ALLOWED_PREFIX):]:
        raise ValueError(f"checkpoint names module class {path!r}; only classes under {ALLOWED_PREFIX!r} load")
    module, _, name = path.rpartition(".")
    cls = getattr(importlib.import_module(module), name, None)
    if not (isinstance(cls, type) and issubclass(cls, L.LightningModule)):
        raise ValueError(f"checkpoint names {path!r}, which is not a LightningModule class of this package")
    return cls


def read_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The checkpoint dict (``path``: a file or a shipped name such as ``difareli_pp-synth64``) (``torch.load(weights_only=True)``), translated to the current format."""
    path = zoo.resolve(path)  # a file, or the name of a shipped checkpoint (difareli.zoo)
    ckpt = load_torch_file(path, "checkpoint", map_location)  # torch.load(weights_only=True), errors name the file
    if "hyper_parameters" not in ckpt or "state_dict" not in ckpt:
        raise ValueError(f"{path} is not a difareli Lightning checkpoint (no hyper_parameters/state_dict)")
    return upgrade_checkpoint(ckpt)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> LoadedCheckpoint:
    """Load a checkpoint with ``torch.load(weights_only=True)`` into the module class it records.

    The weights are the EMA weights when training used the EMA callback (Lightning stores the average in
    ``state_dict``); the config is the model's plain hyperparameters; stats are the non-spatial
    normalisation statistics of the training split (as tensors).
    """
    ckpt = read_checkpoint(path, map_location)
    config = dict(ckpt["hyper_parameters"])
    config.pop("compile", None)  # inference never compiles implicitly
    model = module_class(ckpt[MODULE_KEY])(**config)
    model.load_state_dict(ckpt["state_dict"])
    model.eval().requires_grad_(False)
    model.to(map_location)
    raw = config.get("nonspatial_stats") or {}
    stats = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in raw.items()}
    return LoadedCheckpoint(model=model, config=config, stats=stats, global_step=int(ckpt.get("global_step", 0)))
