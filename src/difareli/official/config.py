"""What an official DiFaReli YAML says about the networks (github.com/diffusion-face-relighting/difareli_code).

The official networks are built from a yacs config: ``config/base_config.py`` defaults merged with
``config/difareli/difareli_{64,128,256}.yaml`` (or a run's dumped, merged config). :func:`read_config` reads one,
refuses what our network cannot reproduce (naming the key), and returns it in our terms as an
:class:`OfficialConfig`; :data:`DEFAULTS` holds the defaults of the keys read here (nothing of the official code is
copied). :mod:`difareli.official.weights` maps the weights of the network such a config describes.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from difareli.checkpoints.format import OFFICIAL_REPO as REPO
from difareli.errors import UserError, check_file

#: The defaults (``config/base_config.py``) of the keys this module reads.
DEFAULTS: dict[str, dict[str, Any]] = {
    "img_model": {"name": "Img", "arch": "UNet", "image_size": 128, "num_channels": 128, "in_channels": 3,
                  "out_channels": 3, "num_res_blocks": 2, "num_heads": 4, "num_heads_upsample": -1,
                  "num_head_channels": -1, "attention_resolutions": "16,8", "channel_mult": "", "dropout": 0.0,
                  "use_scale_shift_norm": True, "resblock_updown": False, "use_new_attention_order": False,
                  "condition_proj_dim": 512, "conditioning": False, "hadamart_prep": None,
                  "cond_layer_selector": None, "apply_dpm_cond_img": False, "in_image": ["raw"]},
    "img_cond_model": {"name": "ImgEncoder", "apply": False, "arch": "EncoderUNet", "in_image": ["raw"],
                       "image_size": 128, "num_channels": 128, "num_res_blocks": 2, "num_heads": 4,
                       "num_head_channels": -1, "attention_resolutions": "16,8", "channel_mult": "", "dropout": 0.0,
                       "resblock_updown": False, "use_new_attention_order": False, "override_cond": "",
                       "prep_image": [None]},
    "param_model": {"params_selector": ["shape", "pose", "exp", "cam", "light", "faceemb"], "rmv_params": []},
    "relighting": {"use_SH": False, "num_SH": 9},
    "diffusion": {"diffusion_steps": 1000, "noise_schedule": "linear", "learn_sigma": False, "predict_xstart": False,
                  "rescale_timesteps": False},
}
#: Width of each non-spatial parameter in ``cond_params`` (base_config's ``params_dict``).
PARAM_WIDTHS = {"shape": 100, "pose": 6, "exp": 50, "cam": 3, "light": 27, "faceemb": 512, "shadow": 1}
#: Our encoding holding each official parameter (DECA shape/pose/exp live in ``shape``, in the store's layout).
PARAM_ENCODING = {"shape": "shape", "pose": "shape", "exp": "shape", "cam": "cam", "light": "light",
                  "faceemb": "identity", "shadow": "shadow"}
#: Our encoding for each Modulator input image (with its channels).
IMAGE_ENCODING = {"deca_masked_face_images_woclip": "shading", "faceseg_nohead": "background"}
#: The official channel multipliers by image size when ``channel_mult`` is empty (``script_util.create_model``).
CHANNEL_MULT = {64: [1, 2, 3, 4], 128: [1, 1, 2, 3, 4], 256: [1, 1, 2, 2, 4, 4]}
_ARCH = ("UNetCond_SpatialCondition_Hadamart", "EncoderUNet_SpatialCondition")
#: Architecture keys the Modulator must share with the UNet (ours mirrors the UNet's first half).
_SHARED = ("image_size", "num_channels", "num_res_blocks", "num_heads", "num_head_channels", "attention_resolutions",
           "channel_mult", "resblock_updown", "use_new_attention_order")
_LISTS = ("attention_resolutions", "channel_mult")


@dataclass
class OfficialConfig:
    """What an official YAML says about the networks, in our terms."""

    path: Path
    cfg: dict[str, Any]
    net: dict[str, Any]             # UNetConfig fields
    spatial_inputs: list[str]
    selector: list[str]             # official non-spatial parameters, in cond_params order
    unet_name: str
    encoder_name: str

    @property
    def nonspatial_inputs(self) -> list[str]:
        return list(dict.fromkeys(PARAM_ENCODING[p] for p in self.selector))


def _merged(raw: Mapping[str, Any]) -> dict[str, Any]:
    cfg = copy.deepcopy(DEFAULTS)
    for section, values in raw.items():
        if isinstance(values, Mapping):
            cfg.setdefault(str(section), {}).update(values)
    return cfg


def _ints(value: Any) -> list[int]:
    """``"16,8"`` (the YAML files), ``(16, 8)`` or ``16`` (yacs' literal_eval of a dumped config) -> ints."""
    items = value if isinstance(value, (list, tuple)) else str(value).split(",")
    return [int(float(v)) for v in items]


def read_config(path: str | Path) -> OfficialConfig:
    """The official YAML (``config/difareli/difareli_128.yaml`` or a run's merged config), validated for import."""
    import yaml

    p = check_file(path, "config")
    try:
        raw = yaml.safe_load(p.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise UserError(f"config={p} is not readable YAML ({str(e).splitlines()[0]}); give the official YAML the "
                        "checkpoint was trained with, e.g. config/difareli/difareli_128.yaml") from None
    if not isinstance(raw, Mapping) or not isinstance(raw.get("img_model"), Mapping):
        raise UserError(f"config={p} is not an official DiFaReli config (no img_model section); give the YAML the "
                        "checkpoint was trained with, e.g. config/difareli/difareli_128.yaml")
    cfg = _merged(raw)
    m, e, d = cfg["img_model"], cfg["img_cond_model"], cfg["diffusion"]

    def need(ok: bool, key: str, value: Any, what: str) -> None:
        if not ok:
            raise UserError(f"config={p}: {key}={value!r} {what}; only the DiFaReli Modulator model of {REPO} "
                            "(config/difareli/*.yaml) imports")

    need(m["arch"] == _ARCH[0], "img_model.arch", m["arch"], f"is not {_ARCH[0]}")
    need(bool(e["apply"]) and e["arch"] == _ARCH[1], "img_cond_model.arch", e["arch"], f"(apply={e['apply']}) is not "
         f"an applied {_ARCH[1]}")
    need(e["override_cond"] == "spatial_latent", "img_cond_model.override_cond", e["override_cond"],
         "is not spatial_latent")
    need(str(m["hadamart_prep"]).lower() == "tanh", "img_model.hadamart_prep", m["hadamart_prep"],
         "is not Tanh (ours gates with tanh(m))")
    need(m["cond_layer_selector"] in (None, "all"), "img_model.cond_layer_selector", m["cond_layer_selector"],
         "modulates only some levels (ours modulates all)")
    need(bool(m["use_scale_shift_norm"]), "img_model.use_scale_shift_norm", m["use_scale_shift_norm"],
         "is not true (ours: (1 + t_s) GN(h) + t_b)")
    need(not m["apply_dpm_cond_img"] and list(m["in_image"]) == ["raw"], "img_model.apply_dpm_cond_img",
         m["apply_dpm_cond_img"], "feeds images to the UNet itself")
    need(m["num_heads_upsample"] in (-1, m["num_heads"]), "img_model.num_heads_upsample", m["num_heads_upsample"],
         "differs from num_heads")
    need((m["in_channels"], m["out_channels"]) == (3, 3) and not d["learn_sigma"] and not d["predict_xstart"],
         "img_model.out_channels", m["out_channels"], "(or learn_sigma / predict_xstart) is not eps on RGB")
    need(d["noise_schedule"] == "linear" and int(d["diffusion_steps"]) == 1000 and not d["rescale_timesteps"],
         "diffusion.noise_schedule", d["noise_schedule"], "(with 1000 steps, unrescaled) is not the linear schedule")
    for key in _SHARED:
        same = (lambda v: _ints(v) if v not in ("", None, ()) else v) if key in _LISTS else (lambda v: v)
        need(same(e.get(key, m[key])) == same(m[key]), f"img_cond_model.{key}", e.get(key),
             f"differs from img_model.{key}={m[key]!r} (ours mirrors the UNet's first half)")
    images = list(e["in_image"])
    preps = list(e.get("prep_image") or [None] * len(images))
    bad = [i for i in images if i not in IMAGE_ENCODING] + [str(x) for x in preps if x is not None]
    need(not bad, "img_cond_model.in_image", images, f"has inputs without a difareli encoding ({bad}); known: "
         f"{sorted(IMAGE_ENCODING)}, no prep_image")
    selector = [s for s in cfg["param_model"]["params_selector"] if s not in cfg["param_model"]["rmv_params"]]
    if not m["conditioning"]:
        selector = []
    unknown = [s for s in selector if s not in PARAM_WIDTHS]
    need(not unknown, "param_model.params_selector", selector, f"names {unknown}, which have no difareli encoding")
    need(int(cfg["relighting"]["num_SH"]) == 9, "relighting.num_SH", cfg["relighting"]["num_SH"], "is not 9")
    size = int(m["image_size"])
    mult = _ints(m["channel_mult"]) if m["channel_mult"] not in ("", None, ()) else CHANNEL_MULT.get(size)
    need(mult is not None, "img_model.image_size", size, f"has no default channel_mult here ({sorted(CHANNEL_MULT)})")
    net = {"base_channels": int(m["num_channels"]), "channel_mult": mult, "num_res_blocks": int(m["num_res_blocks"]),
           "attention_resolutions": _ints(m["attention_resolutions"]), "image_size": size,
           "num_heads": int(m["num_heads"]), "num_head_channels": int(m["num_head_channels"]),
           "dropout": float(m["dropout"]), "resblock_updown": bool(m["resblock_updown"]), "norm_groups": 32,
           "adagn_hidden": int(m["condition_proj_dim"])}
    return OfficialConfig(p, cfg, net, [IMAGE_ENCODING[i] for i in images], selector, str(m["name"]),
                          str(e["name"]))
