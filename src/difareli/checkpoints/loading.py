"""Loading trained models from checkpoints, for notebooks and CLIs: only the package and the file.

A checkpoint records the module class that wrote it and its format (:mod:`difareli.checkpoints.format`, which
also translates older formats); :func:`load_checkpoint` finds that class among the registered ones
(:mod:`difareli.checkpoints.registry`: ``difareli.lit``'s models register themselves as they are defined, so the
loader never imports a layer above its own by a name) and builds it from the plain hyperparameters. A checkpoint
is a ``.ckpt`` file (``torch.load`` with ``weights_only=True``), a weights folder written by ``difareli-export``
(``model.safetensors`` + ``config.json``, :mod:`difareli.checkpoints.export`: no pickle at all), or a shipped name
(its folder when it has one).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import lightning as L
import torch

from difareli.checkpoints import zoo
from difareli.checkpoints.registry import module_class
from difareli.errors import UserError
from difareli.checkpoints.format import (MODULE_KEY, build_module, is_folder, load_torch_file, read_folder,
                                         refuse_official, training_resolution, upgrade_checkpoint)

@dataclass
class LoadedCheckpoint:
    """A model ready for inference plus what it was trained with."""

    model: L.LightningModule
    config: dict[str, Any]
    stats: dict[str, torch.Tensor]
    global_step: int

    @property
    def resolution(self) -> int | None:
        """The image size (px) it was trained at (:func:`~difareli.checkpoints.format.training_resolution`)."""
        return training_resolution(self.config)

    @classmethod
    def of(cls, model: L.LightningModule, config: Mapping[str, Any], global_step: int = 0) -> "LoadedCheckpoint":
        """``model`` with its hyperparameters ``config`` as a loaded checkpoint: the config as inference reads it
        (``compile`` dropped: inference never compiles implicitly) and the normalisation statistics it holds."""
        config = _inference_config(config)
        raw = config.get("nonspatial_stats") or {}
        stats = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in raw.items()}
        return cls(model=model, config=config, stats=stats, global_step=int(global_step))

    @classmethod
    def of_module(cls, module: L.LightningModule, global_step: int = 0) -> "LoadedCheckpoint":
        """A module already in memory (the one in training, an untrained one) as a loaded checkpoint, its own
        hyperparameters the config; nothing is copied."""
        return cls.of(module, getattr(module, "hparams", None) or {}, global_step)


def read_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The checkpoint dict, translated to the current format, of ``path``: a .ckpt file (``torch.load(weights_only=
    True)``), a weights folder (safetensors + JSON, no pickle) or a shipped name such as ``difareli_pp-synth64``
    (its weights folder when shipped, else its .ckpt)."""
    path = zoo.resolve(path, prefer_folder=True)  # a file, a folder, or a shipped name (difareli.checkpoints.zoo)
    if is_folder(path):
        return upgrade_checkpoint(read_folder(path, map_location), path)
    ckpt = load_torch_file(path, "checkpoint", map_location)  # torch.load(weights_only=True), errors name the file
    if "hyper_parameters" not in ckpt or "state_dict" not in ckpt:
        refuse_official(ckpt, path)  # the authors' ImgCond/ImgEncoder .pt: a message naming the import command
        raise UserError(f"{path} is not a difareli Lightning checkpoint (no hyper_parameters/state_dict)")
    return upgrade_checkpoint(ckpt, path)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> LoadedCheckpoint:
    """Load a checkpoint with ``torch.load(weights_only=True)`` into the module class it records.

    The weights are the EMA weights when training used the EMA callback (Lightning stores the average in
    ``state_dict``); the config is the model's plain hyperparameters; stats are the non-spatial
    normalisation statistics of the training split (as tensors).
    """
    ckpt = read_checkpoint(path, map_location)
    config = _inference_config(ckpt["hyper_parameters"])
    model = build_module(module_class(ckpt[MODULE_KEY]), config, ckpt["state_dict"], path)
    model.eval().requires_grad_(False)
    return LoadedCheckpoint.of(model.to(map_location), config, ckpt.get("global_step", 0))


def _inference_config(hparams: Mapping[str, Any]) -> dict[str, Any]:
    # Inference never compiles implicitly: a model trained with compile=true is built without it.
    return {k: v for k, v in dict(hparams).items() if k != "compile"}


def check_resume(ckpt_path: Any, model: Any, ckpt: Mapping[str, Any] | None = None) -> None:
    """Resuming ``model`` from ``ckpt_path``: if state-dict keys or shapes differ, raise a UserError listing
    the differing hyperparameters (or tensors), instead of PyTorch's size-mismatch dump. ``ckpt``: the
    checkpoint dict when the caller has already read it."""
    ckpt = load_torch_file(ckpt_path, "ckpt_path") if ckpt is None else ckpt
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise UserError(f"ckpt_path={ckpt_path} is not a Lightning checkpoint (no state_dict)")
    have = {k: tuple(v.shape) for k, v in ckpt["state_dict"].items() if hasattr(v, "shape")}
    want = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    bad = sorted(k for k in set(have) | set(want) if have.get(k) != want.get(k))
    if not bad:
        return
    saved = dict(ckpt.get("hyper_parameters") or {})
    now = dict(getattr(model, "hparams", {}) or {})
    diff = [f"{k}: checkpoint {saved.get(k)!r}, config {now.get(k)!r}" for k in sorted(set(saved) | set(now))
            if k != "compile" and saved.get(k) != now.get(k)]
    listed = "; ".join(diff[:8]) if diff else f"tensors {', '.join(bad[:5])}"
    raise UserError(f"ckpt_path={ckpt_path} does not match this model config ({len(bad)} tensors differ): "
                    f"{listed}\nresume with the model config it was trained with (see <run>/.hydra/config.yaml)")
