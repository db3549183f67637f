"""Weights as a folder that loads with no pickle at all: ``model.safetensors`` + ``config.json`` + ``README.md``.

- ``model.safetensors``: the module's ``state_dict`` as the checkpoint holds it (the EMA weights the relight uses:
  Lightning stores the EMA average there), serialised with ``safetensors.torch.save`` (a JSON header and raw
  little-endian tensors).
- ``config.json``: what :func:`difareli.checkpoints.loading.load_checkpoint` needs to rebuild the module: the module
  class (``difareli_module``, imported by name), the format version, the plain hyperparameters (the normalisation
  statistics are ``hyper_parameters.nonspatial_stats``), ``global_step``, ``epoch``, the Lightning version and the
  model-card facts, plus where the weights came from (file name and SHA-256).
- ``README.md``: the model card (the shipped one for a shipped checkpoint, else one written from the checkpoint).

:func:`read_folder` reads it back with ``safetensors.torch.load_file`` and ``json``: no ``torch.load``, no pickle;
``config.json`` and the safetensors header are checked first, the tensors when they are loaded into the module
(:mod:`difareli.checkpoints.format`).
The ``.ckpt`` stays the format for resuming training (optimizer state, callbacks); a folder is for inference.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

# The folder's layout and its reader live below the loaders (checkpoints/format.py); re-exported here.
from difareli.checkpoints.format import (  # noqa: F401
    CARD, CONFIG, CONFIG_KEYS, FOLDER_FORMAT, FOLDER_VERSION, WEIGHTS, is_folder, read_folder)
from difareli.errors import UserError, is_no_space
from difareli.checkpoints import loading, zoo
from difareli.utils.fileio import fsync_dir, no_space


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def export_folder(checkpoint: str | Path, folder: str | Path) -> Path:
    """Write the weights folder of ``checkpoint`` (a .ckpt file or a shipped name) into ``folder``; returns it.

    ``folder`` must be new, empty or an earlier weights folder (replaced whole). A source holding NaN/Inf weights is
    refused before anything is written. The three files are written into a scratch folder beside ``folder`` and
    renamed into place together, so a failure (a full disk, a kill) never leaves a partial or mixed folder."""
    source = loading.resolve(checkpoint)
    if source.is_dir():
        raise UserError(f"checkpoint={checkpoint} is already a weights folder ({source}); copy it instead")
    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or (any(folder.iterdir()) and not is_folder(folder))):
        raise UserError(f"{folder} exists and is not an empty folder or a weights folder; give a new folder")
    ckpt = loading.read_checkpoint(source)
    loading.check_finite_state(ckpt["state_dict"], f"checkpoint={checkpoint}", "a folder of it would not load, so "
                               "nothing was written: export a checkpoint whose weights are finite (an earlier step's)")
    stage = folder.parent / f".{folder.name}.partial-{os.getpid()}"
    try:
        stage.mkdir(parents=True)
        _write_files(ckpt, source, stage, folder.name)
        _publish(stage, folder)
    except OSError as e:
        shutil.rmtree(stage, ignore_errors=True)
        if is_no_space(e):
            name = Path(e.filename).name if e.filename else folder.name
            raise no_space(folder / name if e.filename else folder, e, "free space or export elsewhere (nothing "
                           "was written)") from None
        raise
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return folder


def _write_files(ckpt: dict, source: Path, stage: Path, name: str) -> None:
    """model.safetensors, config.json and README.md of ``ckpt`` into ``stage``."""
    from safetensors.torch import save

    # Own contiguous copies: safetensors refuses tensors that share storage or are strided views.
    state = {k: v.detach().to("cpu").contiguous().clone() for k, v in ckpt["state_dict"].items()}
    # Serialised here and written by Python, so a full disk is an OSError naming the file (ENOSPC).
    (stage / WEIGHTS).write_bytes(save(state, metadata={"format": FOLDER_FORMAT}))
    os.chmod(stage / WEIGHTS, 0o644)  # package data: readable by all, as the .ckpt files beside it
    config = {"format": FOLDER_FORMAT, "version": FOLDER_VERSION,
              "source": {"file": source.name, "sha256": _sha256(source)},
              **{k: ckpt[k] for k in CONFIG_KEYS if k in ckpt}}
    (stage / CONFIG).write_text(json.dumps(config, indent=1, sort_keys=True, allow_nan=True) + "\n")
    shipped = source.parent == zoo.SHIPPED_DIR and (zoo.SHIPPED_DIR / f"{source.stem}.md").is_file()
    card = zoo.card(source.stem) if shipped else zoo.model_card(name, ckpt, ckpt.get("model_card") or {})
    (stage / CARD).write_text(card)


def _publish(stage: Path, folder: Path) -> None:
    """Rename the finished ``stage`` onto ``folder`` (absent, empty, or an earlier weights folder, moved aside
    first and removed after): renames need no space, and ``folder`` is never half old, half new."""
    old = None
    if folder.is_dir() and any(folder.iterdir()):
        old = folder.parent / f".{folder.name}.old-{os.getpid()}"
        os.replace(folder, old)
    elif folder.is_dir():
        folder.rmdir()
    os.replace(stage, folder)
    fsync_dir(folder.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
