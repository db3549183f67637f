"""Weights as a folder that loads with no pickle at all: ``model.safetensors`` + ``config.json`` + ``README.md``.

- ``model.safetensors``: the module's ``state_dict`` as the checkpoint holds it (the EMA weights the relight uses:
  Lightning stores the EMA average there), written with ``safetensors.torch.save_file`` (a JSON header and raw
  little-endian tensors).
- ``config.json``: what :func:`difareli.checkpoints.loading.load_checkpoint` needs to rebuild the module: the module
  class (``difareli_module``, imported by name), the format version, the plain hyperparameters (the normalisation
  statistics are ``hyper_parameters.nonspatial_stats``), ``global_step``, ``epoch``, the Lightning version and the
  model-card facts, plus where the weights came from (file name and SHA-256).
- ``README.md``: the model card (the shipped one for a shipped checkpoint, else one written from the checkpoint).

:func:`read_folder` reads it back with ``safetensors.torch.load_file`` and ``json``: no ``torch.load``, no pickle.
The ``.ckpt`` stays the format for resuming training (optimizer state, callbacks); a folder is for inference.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

# The folder's layout and its reader live below the loaders (checkpoints/format.py); re-exported here.
from difareli.checkpoints.format import (  # noqa: F401
    CARD, CONFIG, CONFIG_KEYS, FOLDER_FORMAT, FOLDER_VERSION, WEIGHTS, is_folder, read_folder)
from difareli.errors import UserError
from difareli.checkpoints import zoo
from difareli.utils.fileio import atomic_path, write_text_atomic


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def export_folder(checkpoint: str | Path, folder: str | Path) -> Path:
    """Write the weights folder of ``checkpoint`` (a .ckpt file or a shipped name) into ``folder``; returns it.

    ``folder`` must be new, empty or an earlier weights folder (its three files are replaced). Each file is written
    to a temporary name beside it and renamed, so a failed export never leaves a half-written file."""
    from safetensors.torch import save_file

    from difareli.checkpoints.loading import read_checkpoint
    source = zoo.resolve(checkpoint)
    if source.is_dir():
        raise UserError(f"checkpoint={checkpoint} is already a weights folder ({source}); copy it instead")
    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or (any(folder.iterdir()) and not is_folder(folder))):
        raise UserError(f"{folder} exists and is not an empty folder or a weights folder; give a new folder")
    ckpt = read_checkpoint(source)
    folder.mkdir(parents=True, exist_ok=True)
    # Own contiguous copies: safetensors refuses tensors that share storage or are strided views.
    state = {k: v.detach().to("cpu").contiguous().clone() for k, v in ckpt["state_dict"].items()}
    with atomic_path(folder / WEIGHTS) as tmp:
        save_file(state, str(tmp), metadata={"format": FOLDER_FORMAT})
        os.chmod(tmp, 0o644)  # package data: readable by all, as the .ckpt files beside it
    config = {"format": FOLDER_FORMAT, "version": FOLDER_VERSION,
              "source": {"file": source.name, "sha256": _sha256(source)},
              **{k: ckpt[k] for k in CONFIG_KEYS if k in ckpt}}
    write_text_atomic(folder / CONFIG, json.dumps(config, indent=1, sort_keys=True, allow_nan=True) + "\n")
    shipped = source.parent == zoo.SHIPPED_DIR and (zoo.SHIPPED_DIR / f"{source.stem}.md").is_file()
    card = zoo.card(source.stem) if shipped else zoo.model_card(folder.name, ckpt, ckpt.get("model_card") or {})
    write_text_atomic(folder / CARD, card)
    return folder
