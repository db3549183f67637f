"""The checkpoint format: the keys difareli writes beside Lightning's, which keys a slim (shipped) checkpoint
keeps, the translation of older formats, and the two files a checkpoint is stored as: a ``.ckpt`` (any torch file,
read with ``torch.load(weights_only=True)``: :func:`load_torch_file`) and a weights folder (``model.safetensors`` +
``config.json`` + ``README.md``, written by :mod:`difareli.checkpoints.export`; read with no pickle at all:
:func:`read_folder`). Used by the Lightning modules, :mod:`difareli.checkpoints.loading`,
:mod:`difareli.checkpoints.zoo` and the authors' weights' import; nothing here imports any of them.

Checkpoints written before format 2 (flat ``spatial_type`` / ``modulate_skips`` / ``lr`` / ``weight_decay``,
statistics in ``state_dict`` buffers) are translated by :func:`upgrade_checkpoint`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import torch

from difareli.errors import UserError, UserFileNotFoundError

#: The module class that wrote a checkpoint (``package.module.Class``) and the format version.
MODULE_KEY, FORMAT_KEY, FORMAT_VERSION = "difareli_module", "difareli_format", 2
#: The class of checkpoints that predate ``difareli_module`` (all of them were DiffusionModules).
LEGACY_MODULE = "difareli.lit.diffusion.DiffusionModule"
#: Keys a slim checkpoint keeps from a Lightning checkpoint.
SLIM_KEYS = ("state_dict", "hyper_parameters", "global_step", "epoch", MODULE_KEY, FORMAT_KEY,
             "pytorch-lightning_version")


def stamp(checkpoint: dict[str, Any], module: object) -> None:
    """Record ``module``'s class and the current format in a checkpoint dict being saved."""
    checkpoint[MODULE_KEY] = f"{type(module).__module__}.{type(module).__qualname__}"
    checkpoint[FORMAT_KEY] = FORMAT_VERSION


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


# ---------------------------------------------------------------------------------------------- official files
#: The official DiFaReli code, whose checkpoints difareli-import-checkpoint converts (difareli.official.weights).
OFFICIAL_REPO = "github.com/diffusion-face-relighting/difareli_code"


def is_official(obj: Any) -> str | None:
    """``"unet"`` / ``"modulator"`` if ``obj`` is an official state dict (UNet / Modulator), else None."""
    if not isinstance(obj, Mapping) or "hyper_parameters" in obj or "input_blocks.0.0.weight" not in obj:
        return None
    return "unet" if "time_embed.0.weight" in obj else "modulator"


def refuse_official(obj: Any, path: Any) -> None:
    """Raise the one-line message that names the import command when ``obj`` (loaded from ``path``) is an
    official state dict; a no-op otherwise. Every loader (``lit.read_checkpoint``) calls it."""
    role = is_official(obj)
    if role is not None:
        raise UserError(f"checkpoint={path} is an official DiFaReli {role} state dict ({OFFICIAL_REPO}); convert it "
                        f"once: difareli-import-checkpoint {path} config=<its official YAML> out=<name>.ckpt, then "
                        "use checkpoint=<name>.ckpt")


def training_resolution(config: Mapping[str, Any] | None) -> int | None:
    """The image size (px) a checkpoint was trained at, from its hyperparameters (``input_dims.resolution``, which
    difareli-train takes from the DataModule), or None where it records none."""
    dims = dict((config or {}).get("input_dims") or {})
    res = dims.get("resolution")
    return int(res) if res else None


# ---------------------------------------------------------------------------------------------- files
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
