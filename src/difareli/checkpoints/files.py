"""Reading a checkpoint's files: a ``.ckpt`` (or any torch file) with ``torch.load(weights_only=True)``, and a
weights folder (``model.safetensors`` + ``config.json`` + ``README.md``, written by
:mod:`difareli.checkpoints.export`; no ``torch.load``, no pickle). What loading a checkpoint, resolving a shipped
name and importing the authors' weights need, below all of them, so none imports the writer."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from difareli.checkpoints.format import FORMAT_KEY, MODULE_KEY
from difareli.errors import UserError, UserFileNotFoundError

WEIGHTS, CONFIG, CARD = "model.safetensors", "config.json", "README.md"
#: ``config.json``'s ``format``: what wrote the folder, so another folder with a config.json is never mistaken.
FOLDER_FORMAT = "difareli-weights-folder"
FOLDER_VERSION = 1
#: Checkpoint keys config.json carries (besides the state dict, which goes to model.safetensors).
CONFIG_KEYS = ("hyper_parameters", "global_step", "epoch", MODULE_KEY, FORMAT_KEY, "pytorch-lightning_version",
               "model_card")


def is_folder(path: str | Path) -> bool:
    """Whether ``path`` is a weights folder (a directory holding :data:`WEIGHTS` and :data:`CONFIG`)."""
    p = Path(path)
    return p.is_dir() and (p / WEIGHTS).is_file() and (p / CONFIG).is_file()


def read_folder(folder: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The checkpoint dict of a weights folder (``state_dict`` from safetensors, the rest from JSON); no pickle."""
    from safetensors.torch import load_file

    folder = Path(folder)
    try:
        config = json.loads((folder / CONFIG).read_text())
    except (OSError, ValueError) as e:
        raise UserError(f"{folder / CONFIG}: unreadable ({e}); export the folder again: difareli-export "
                        f"<checkpoint> {folder}") from None
    if not isinstance(config, dict) or config.get("format") != FOLDER_FORMAT:
        raise UserError(f"{folder / CONFIG} is not a difareli weights folder's config (no \"format\": "
                        f"\"{FOLDER_FORMAT}\"); make one with difareli-export <checkpoint> <folder>")
    if int(config.get("version", 0)) > FOLDER_VERSION:
        raise UserError(f"{folder} is a weights folder of version {config.get('version')}, newer than this "
                        f"difareli reads ({FOLDER_VERSION}); load it with the difareli version that wrote it")
    device = str(torch.device(map_location)) if not isinstance(map_location, str) else map_location
    ckpt = {k: config[k] for k in CONFIG_KEYS if k in config}
    ckpt["state_dict"] = load_file(folder / WEIGHTS, device=device)
    return ckpt


def load_torch_file(path: Any, what: str = "checkpoint", map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)``; a missing, truncated or non-torch file is a UserError naming
    it (never a hint to load untrusted pickles)."""
    import torch

    p = Path(str(path))
    if not p.is_file():
        raise UserFileNotFoundError(f"{what} {p} does not exist (difareli-train writes <run>/checkpoints/last.ckpt)")
    try:
        return torch.load(p, map_location=map_location, weights_only=True)
    except Exception as e:  # random bytes reach the unpickler's internals: KeyError, struct.error, ...
        size = p.stat().st_size
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if "weights_only" in first or "Weights only load failed" in first:
            first = "it holds objects other than tensors and plain containers"
        raise UserError(f"{what} {p} ({size} bytes) is not a readable PyTorch file ({first[:160]}); it may be "
                        "truncated or corrupt: copy it again or use another checkpoint") from None
