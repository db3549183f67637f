"""The checkpoint format: the keys difareli writes beside Lightning's, which keys a slim (shipped) checkpoint
keeps, and the translation of older formats. Plain dict work: written by the Lightning modules, read by
:mod:`difareli.checkpoints.loading` and :mod:`difareli.checkpoints.zoo`, nothing here imports either.

Checkpoints written before format 2 (flat ``spatial_type`` / ``modulate_skips`` / ``lr`` / ``weight_decay``,
statistics in ``state_dict`` buffers) are translated by :func:`upgrade_checkpoint`.
"""

from __future__ import annotations

from typing import Any, Mapping

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
    from collections.abc import Mapping

    if not isinstance(obj, Mapping) or "hyper_parameters" in obj or "input_blocks.0.0.weight" not in obj:
        return None
    return "unet" if "time_embed.0.weight" in obj else "modulator"


def refuse_official(obj: Any, path: Any) -> None:
    """Raise the one-line message that names the import command when ``obj`` (loaded from ``path``) is an
    official state dict; a no-op otherwise. Every loader (``lit.read_checkpoint``) calls it."""
    from difareli.errors import UserError

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
