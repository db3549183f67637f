"""The authors' DiFaReli checkpoints (github.com/diffusion-face-relighting/difareli_code) as difareli checkpoints.

(:mod:`difareli.official.importers` imports that code's *preprocessing output* into a store; this module its *weights*.)

What the official code writes, read from that repository (nothing of it is copied here):

- training saves every network of the model dict as its own plain state dict (``th.save(state_dict)``):
  ``<img_model.name>_ema_<rate>_<step>.pt`` (the UNet, ``ImgCond``) and ``<img_cond_model.name>_ema_...pt`` (the
  Modulator, ``ImgEncoder``), beside ``..._model<step>.pt`` (raw weights) and ``opt<step>.pt``. They hold only
  tensors, so they load with ``torch.load(weights_only=True)``;
- the networks are built from a yacs config, read by :func:`difareli.official.config.read_config`;
- ``UNetModel_SpatialCondition_Hadamart``: guided-diffusion names (``input_blocks`` / ``middle_block`` /
  ``output_blocks``, ``in_layers`` / ``emb_layers`` / ``out_layers`` / ``skip_connection``), the AdaGN MLP3 as
  ``cond_proj_layers``, and a parameter-free ``HadamartLayer`` (``x * tanh(m)``) as layer 0 of every input block
  but the first and at both ends of the middle block; ``EncoderUNet_SpatialCondition`` (the Modulator) has the same
  layout without the time path and without Hadamart layers;
- attention with ``use_new_attention_order=False`` (the default) lays the qkv rows out per head, ``[q_h, k_h,
  v_h]`` for each head h; ours (the "new" order) lays out ``[q, k, v]`` over all heads;
- the non-spatial vector ``cond_params`` is the concatenation of ``param_model.params_selector`` (minus
  ``rmv_params``) with the widths of :data:`~difareli.official.config.PARAM_WIDTHS`, raw (no normalisation); the
  Modulator reads ``img_cond_model.in_image`` concatenated in that order.

Mapping: :func:`convert` renames (Hadamart layers dropped, so later layer indices shift by one), reorders the
legacy q/k/v rows, and permutes the first MLP3 columns from the official vector order to ours (``shape`` holds
the DECA parts in the store's ``shape_layout``; parts the checkpoint never saw get zero weights). Every tensor of
our network must be filled with the right shape, else the file is refused naming the tensor.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from difareli.checkpoints.format import OFFICIAL_REPO as REPO
from difareli.checkpoints.format import is_official, load_torch_file, stamp
from difareli.checkpoints.loading import load_checkpoint
from difareli.errors import UserError, check_file, check_out_dir
# read_config and PARAM_WIDTHS are also named from here (scripts/bench_official.py, docs/official_code.md).
from difareli.official.config import DEFAULTS, PARAM_ENCODING, PARAM_WIDTHS, OfficialConfig, read_config
from difareli.utils.fileio import torch_save_atomic
from difareli.official import safety
from difareli.data import encodings
from difareli.data.store import EncodingStore
from difareli.nn.presets import get_config

#: ``shape``'s part order in a store written by ``difareli.official.importers`` (its default ``shape_parts``).
STORE_SHAPE_PARTS = ("shape", "exp", "pose")


# ---------------------------------------------------------------------------------------------- files
def _load(path: Path, what: str) -> dict[str, Any]:
    obj = load_torch_file(path, what)
    if isinstance(obj, Mapping) and "hyper_parameters" in obj and "state_dict" in obj:
        raise UserError(f"{what}={path} is already a difareli checkpoint; use it directly: checkpoint={path}")
    if isinstance(obj, Mapping) and set(obj) == {"state_dict"}:
        obj = obj["state_dict"]
    if is_official(obj) is None or not all(hasattr(v, "shape") for v in obj.values()):
        raise UserError(f"{what}={path} holds no official DiFaReli weights (expected a state dict with keys such as "
                        "input_blocks.0.0.weight); give the authors' <name>_ema_0.9999_<step>.pt")
    return dict(obj)


_STEM = re.compile(r"^(?P<name>.+?)_(?P<kind>ema_[0-9.]+_|model)(?P<step>\d+)\.pt$")


def find_files(path: str | Path, cfg: OfficialConfig, encoder: str | Path | None = None, step: int | None = None,
               ema: str = "0.9999") -> tuple[Path, Path, int]:
    """``(UNet file, Modulator file, step)`` from a file of either network, or a folder of a training run (the
    highest step of ``<name>_ema_<ema>_<step>.pt`` unless ``step``); the Modulator is found by name beside it."""
    p = Path(str(path)).expanduser()
    if p.is_dir():
        kind = "model" if ema == "model" else f"ema_{ema}_"
        runs = sorted((int(m["step"]), f) for f in p.glob(f"{cfg.unet_name}_*.pt")
                      if (m := _STEM.match(f.name)) and m["kind"] == kind and (step is None or int(m["step"]) == step))
        if not runs:
            want = f"{cfg.unet_name}_{kind}{'<step>' if step is None else f'{step:06d}'}.pt"
            raise UserError(f"official={p} has no {want}; give the UNet file itself or the folder holding it")
        p = runs[-1][1]
    p = check_file(p, "official")
    m = _STEM.match(p.name)
    got = int(m["step"]) if m else 0
    if encoder is not None:
        return p, check_file(encoder, "encoder"), got
    names = (cfg.unet_name, cfg.encoder_name)
    if m and m["name"] in names:
        other = p.with_name(p.name.replace(m["name"], names[1 - names.index(m["name"])], 1))
        if other.is_file():
            return (p, other, got) if m["name"] == names[0] else (other, p, got)
        raise UserError(f"official={p}: no {other.name} beside it; the authors save the UNet ({names[0]}_...) and "
                        f"its Modulator ({names[1]}_...) as two files: give the other with encoder=<path>")
    raise UserError(f"official={p}: cannot tell its Modulator file from the name (expected {names[0]}_ema_0.9999_"
                    "<step>.pt); give it with encoder=<path>")


# ---------------------------------------------------------------------------------------------- mapping
_RES = {"in_layers.0": "in_norm", "in_layers.2": "in_conv", "emb_layers.1": "out_norm.time.1",
        "cond_proj_layers.0": "out_norm.mlp.0", "cond_proj_layers.2": "out_norm.mlp.2",
        "cond_proj_layers.4": "out_norm.mlp.4", "out_layers.3": "out_conv", "skip_connection": "skip", "op": "conv"}
_KEY = re.compile(r"^(?P<block>input_blocks\.\d+|middle_block|output_blocks\.\d+)\.(?P<layer>\d+)\.(?P<rest>.+)$")


def map_name(name: str, role: str) -> str:
    """Our parameter name (under ``net.unet.`` / ``net.spatial.``) for an official one of the UNet or Modulator."""
    prefix = "net.unet." if role == "unet" else "net.spatial."
    m = _KEY.match(name)
    if m is None:
        return prefix + name  # time_embed.*, out.*: same names
    block, layer, rest = m["block"], int(m["layer"]), m["rest"]
    # the UNet's Hadamart layers (no parameters) sit at index 0 of every input block but the first and of the middle
    if role == "unet" and block != "input_blocks.0" and not block.startswith("output_blocks"):
        layer -= 1
    head, _, tail = rest.rpartition(".")
    for old, new in _RES.items():
        if head == old or head.startswith(old + "."):
            head = new + head[len(old):]
            break
    else:
        if head == "out_layers.0":  # the second GroupNorm: AdaGN's in the UNet, a plain one in the Modulator
            head = "out_norm.norm" if role == "unet" else "out_norm"
    return f"{prefix}{block}.{layer}.{head + '.' if head else ''}{tail}"


def legacy_qkv(t: Any, heads: int) -> Any:
    """qkv rows ``[q_h, k_h, v_h]`` per head (legacy order) -> ``[q, k, v]`` over all heads (ours)."""
    c3 = t.shape[0]
    return t.reshape(heads, 3, c3 // (3 * heads), *t.shape[1:]).transpose(0, 1).reshape(t.shape)


def nonspatial_columns(selector: Sequence[str], inputs: Sequence[str], shape_parts: Sequence[str]
                       ) -> tuple[list[int], list[int], int]:
    """``(our columns, official columns, our width)``: where each official ``cond_params`` column goes in our
    vector (``inputs`` concatenated, ``shape`` holding ``shape_parts``)."""
    off, start = {}, 0
    for p in selector:
        off[p] = range(start, start + PARAM_WIDTHS[p])
        start += PARAM_WIDTHS[p]
    ours, theirs, pos = [], [], 0
    unknown = [p for p in shape_parts if PARAM_ENCODING.get(p) != "shape"]
    if unknown or len(set(shape_parts)) != len(shape_parts):
        raise UserError(f"shape_parts={list(shape_parts)}: each of shape, pose, exp at most once (unknown: {unknown})"
                        "; e.g. shape_parts=shape,exp,pose")
    missing = [p for p in selector if PARAM_ENCODING[p] == "shape" and p not in shape_parts]
    if missing:
        raise UserError(f"shape_parts={list(shape_parts)} lacks {missing}, which the checkpoint reads; give the "
                        "store's shape layout (store.json meta shape_layout), e.g. shape_parts=shape,exp,pose")
    for enc in inputs:
        parts = [p for p in shape_parts] if enc == "shape" else [p for p in selector if PARAM_ENCODING[p] == enc]
        for p in parts:
            if p in off:
                ours += range(pos, pos + PARAM_WIDTHS[p])
                theirs += off[p]
            pos += PARAM_WIDTHS[p]
    return ours, theirs, pos


# ---------------------------------------------------------------------------------------------- conversion
def _preset(net: Mapping[str, Any]) -> tuple[str, dict[str, Any]]:
    """The preset this network is (no overrides), else ffhq128 with the fields that differ."""
    def diff(name: str) -> dict[str, Any]:
        base = get_config(name, {"image_size": net["image_size"]})
        return {k: v for k, v in net.items() if k != "image_size" and getattr(base, k) != v}

    for name in ("ffhq128", "ffhq256", "small", "tiny"):
        if not diff(name):
            return name, {}
    return "ffhq128", diff("ffhq128")


def hyper_parameters(cfg: OfficialConfig, shape_parts: Sequence[str] = STORE_SHAPE_PARTS) -> dict[str, Any]:
    """The :class:`~difareli.lit.DiffusionModule` arguments of the official network (raw non-spatial vector:
    identity statistics, as the official code feeds ``cond_params`` unnormalised)."""
    inputs = cfg.nonspatial_inputs
    width = nonspatial_columns(cfg.selector, inputs, shape_parts)[2] if cfg.selector else 0
    channels = sum(encodings.channels(e, {"H": 1, "W": 1}) for e in cfg.spatial_inputs)
    preset, overrides = _preset(cfg.net)
    ours = (cfg.spatial_inputs, inputs) == (["shading", "background"], ["shape", "cam", "identity", "shadow"])
    return {"name": "difareli" if ours else "difareli-official", "preset": preset,
            "spatial": {"type": "modulator", "modulate_skips": False}, "spatial_inputs": list(cfg.spatial_inputs),
            "nonspatial_inputs": inputs, "nonspatial": {"type": "adagn"},
            "input_dims": {"spatial_channels": channels, "nonspatial_dim": width, "resolution": cfg.net["image_size"]},
            "adagn_scale_plus_one": True, "adagn_out_silu": True, "net_overrides": overrides,
            "schedule": {"T": 1000, "beta_start": 1e-4, "beta_end": 0.02}, "nonspatial_stats": None}


def _heads(cfg: OfficialConfig, channels: int) -> int:
    per = cfg.net["num_head_channels"]
    return channels // per if per > 0 else cfg.net["num_heads"]


def convert(unet_sd: Mapping[str, Any], modulator_sd: Mapping[str, Any], cfg: OfficialConfig, *,
            shape_parts: Sequence[str] = STORE_SHAPE_PARTS, step: int = 0,
            files: Mapping[str, str] | None = None) -> tuple[dict[str, Any], Any]:
    """``(difareli checkpoint dict, the DiffusionModule holding the weights)`` from the two official state dicts;
    a tensor missing, left over or of the wrong shape is a UserError naming it and the file it belongs to."""
    import torch

    from difareli.lit.diffusion import DiffusionModule

    files = dict(files or {"unet": "the UNet file", "modulator": "the Modulator file"})
    module = DiffusionModule(**hyper_parameters(cfg, shape_parts))
    want = module.state_dict()
    legacy = not cfg.cfg["img_model"]["use_new_attention_order"]
    ours_cols, their_cols, width = (nonspatial_columns(cfg.selector, module.nonspatial_inputs, shape_parts)
                                    if cfg.selector else ([], [], 0))
    mapped, origin = {}, {}
    for role, sd in (("unet", unet_sd), ("modulator", modulator_sd)):
        for key, value in sd.items():
            name = map_name(key, role)
            v = value.detach().to(torch.float32) if value.is_floating_point() else value.detach()
            if legacy and key.endswith(("qkv.weight", "qkv.bias")) and v.shape[0] % 3 == 0:
                v = legacy_qkv(v, _heads(cfg, v.shape[0] // 3))
            if name.endswith("out_norm.mlp.0.weight") and v.ndim == 2:
                if v.shape[1] != len(their_cols):
                    raise UserError(f"{files[role]}: {key} reads a {v.shape[1]}-wide cond_params, but config="
                                    f"{cfg.path} selects {cfg.selector} ({len(their_cols)} values); give the YAML "
                                    "this checkpoint was trained with")
                w = v.new_zeros(v.shape[0], width)
                w[:, ours_cols] = v[:, their_cols]
                v = w
            mapped[name], origin[name] = v, (role, key)
    extra = [k for k in mapped if k not in want]
    missing = [k for k in want if k not in mapped]
    if extra or missing:
        role = origin[extra[0]][0] if extra else ("unet" if missing[0].startswith("net.unet.") else "modulator")
        what = (f"has {len(extra)} tensor(s) this config's network lacks ({', '.join(origin[k][1] for k in extra[:3])})"
                if extra else f"lacks {len(missing)} tensor(s) ({', '.join(missing[:3])})")
        raise UserError(f"{files[role]} {what}: the file is partial or from another config than config={cfg.path}; "
                        "copy it again or give the YAML it was trained with")
    for k, v in want.items():
        if tuple(mapped[k].shape) != tuple(v.shape):
            role, key = origin[k]
            raise UserError(f"{files[role]}: {key} has shape {tuple(mapped[k].shape)}, config={cfg.path} implies "
                            f"{tuple(v.shape)}; give the YAML this checkpoint was trained with")
    module.load_state_dict(mapped, strict=True)
    module.eval().requires_grad_(False)
    ckpt = {"state_dict": {k: mapped[k] for k in want}, "global_step": int(step), "epoch": 0,
            "hyper_parameters": json.loads(json.dumps(dict(module.hparams))),
            "imported_from": {"repo": REPO, "config": cfg.path.name, "selector": list(cfg.selector),
                              "shape_parts": list(shape_parts), **{k: Path(v).name for k, v in files.items()}}}
    stamp(ckpt, module)
    return ckpt, module


def shape_parts_of(store: str | Path) -> list[str]:
    """The part order of ``shape`` in a store written by :mod:`difareli.official.importers` (its ``shape_layout``
    meta)."""
    layout = EncodingStore.open(store).store_meta.get("shape_layout")
    if not layout:
        raise UserError(f"store={store} records no shape_layout (not written by difareli.official.importers); give "
                        "shape_parts=shape,exp,pose (the order of the DECA parts in its shape encoding)")
    return [k for k, _ in sorted(layout.items(), key=lambda kv: kv[1][0])]


def import_checkpoint(official: str | Path, config: str | Path, out: str | Path, *, encoder: str | Path | None = None,
                      step: int | None = None, ema: str = "0.9999", shape_parts: Sequence[str] | None = None,
                      verify: bool = True) -> dict[str, Any]:
    """Convert an official UNet + Modulator pair to a difareli checkpoint at ``out`` (written atomically) and,
    with ``verify``, check that ``load_checkpoint(out)`` predicts exactly the eps of the converted network."""
    cfg = read_config(config)
    out = Path(str(out))
    check_out_dir(out.parent if str(out.parent) else ".", "out")
    unet_file, mod_file, got = find_files(official, cfg, encoder, step, ema)
    safety.check_out(out, {"official": unet_file, "encoder": mod_file, "config": cfg.path})  # before any write
    parts = list(shape_parts or STORE_SHAPE_PARTS)
    unet_sd, mod_sd = _load(unet_file, "official"), _load(mod_file, "encoder")
    if is_official(unet_sd) != "unet" or is_official(mod_sd) != "modulator":
        unet_sd, mod_sd = (mod_sd, unet_sd) if is_official(mod_sd) == "unet" else (unet_sd, mod_sd)
        unet_file, mod_file = (mod_file, unet_file) if is_official(unet_sd) == "unet" else (unet_file, mod_file)
    if is_official(unet_sd) != "unet" or is_official(mod_sd) != "modulator":
        raise UserError(f"official={unet_file} and encoder={mod_file} are not one UNet ({cfg.unet_name}) and one "
                        f"Modulator ({cfg.encoder_name}) state dict; give the two files of one training step")
    safety.check_finite(unet_sd, unet_file)
    safety.check_finite(mod_sd, mod_file)
    ckpt, module = convert(unet_sd, mod_sd, cfg, shape_parts=parts, step=got,
                           files={"unet": str(unet_file), "modulator": str(mod_file)})
    out.parent.mkdir(parents=True, exist_ok=True)
    torch_save_atomic(ckpt, out)
    summary = {"out": str(out), "unet": str(unet_file), "modulator": str(mod_file), "step": got,
               "parameters": sum(v.numel() for v in ckpt["state_dict"].values()),
               "spatial_inputs": module.spatial_inputs, "nonspatial_inputs": module.nonspatial_inputs,
               "shape_parts": parts, "input_dims": ckpt["hyper_parameters"]["input_dims"],
               "config_notes": safety.config_notes(cfg.cfg, DEFAULTS),
               "warnings": [w for w in [safety.step_warning(unet_file, mod_file)] if w]}
    if verify:
        summary["max_abs_diff"] = verify_loaded(module, out)
        safety.check_verified(summary["max_abs_diff"], out)
    return summary


def verify_loaded(module: Any, path: str | Path, seed: int = 0) -> float:
    """Max |eps difference| between ``module`` and ``load_checkpoint(path)`` (the normal way) on random inputs
    at the training resolution: 0.0 when the file holds exactly the converted weights."""
    import torch


    loaded = load_checkpoint(path).model
    g = torch.Generator().manual_seed(seed)
    dims = module.hparams["input_dims"]
    r = dims["resolution"]
    x = torch.randn(1, 3, r, r, generator=g)
    sp = torch.randn(1, dims["spatial_channels"], r, r, generator=g)
    ns = torch.randn(1, dims["nonspatial_dim"], generator=g) if dims["nonspatial_dim"] else None
    t = torch.tensor([500])
    with torch.no_grad():
        a = module.net(x, t, module.condition(sp, ns))
        b = loaded.net(x, t, loaded.condition(sp, ns))
    return float((a - b).abs().max())
