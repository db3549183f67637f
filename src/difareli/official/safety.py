"""What difareli-import-checkpoint refuses or says before it writes: non-finite weights, an ``out=``
that is one of the inputs or a folder, the UNet and Modulator of different training steps, and the config keys
the tensors cannot show (a wrong YAML with the same shapes would import silently)."""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from difareli.errors import UserError

_STEP = re.compile(r"_(ema_[0-9.]+_|model)(\d+)\.pt$")
#: Config keys that change the network's behaviour without changing any tensor's shape.
SHAPELESS = (("img_model", "num_heads"), ("img_model", "num_head_channels"), ("img_model", "use_new_attention_order"),
             ("img_model", "dropout"), ("img_model", "hadamart_prep"), ("param_model", "params_selector"),
             ("param_model", "rmv_params"), ("img_cond_model", "in_image"))


def check_out(out: Path, inputs: Mapping[str, Path]) -> None:
    """Refuse ``out=`` when it is an existing folder or the same file as one of ``inputs`` (key -> path): writing
    there would replace the authors' weights or a config. Nothing has been written yet."""
    if out.is_dir():
        raise UserError(f"out={out} is a folder; give a file name for the checkpoint, e.g. out={out / 'imported.ckpt'}")
    real = os.path.realpath(out)
    for key, path in inputs.items():
        if path is not None and os.path.realpath(path) == real:
            raise UserError(f"out={out} is the {key} file itself; writing it would replace the input: give a new "
                            "file name, e.g. out=difareli_official.ckpt")


def check_finite(state: Mapping[str, Any], file: Path) -> None:
    """Refuse a state dict holding NaN or Inf (a diverged or corrupt run imports to a model that outputs NaN)."""
    import torch

    for key, value in state.items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            bad = int((~torch.isfinite(value)).sum())
            raise UserError(f"{file}: {key} holds {bad} NaN/Inf value(s) of {value.numel()}; the weights are corrupt "
                            "or the run diverged: copy the file again or take another step's file")


def step_warning(unet: Path, modulator: Path) -> str | None:
    """One line when the two files' names say different training steps (or raw vs EMA weights), else None."""
    a, b = _STEP.search(unet.name), _STEP.search(modulator.name)
    if a is None or b is None or (a[1], int(a[2])) == (b[1], int(b[2])):
        return None
    return (f"warning: the UNet {unet.name} and the Modulator {modulator.name} come from different steps or weights "
            f"({a[1]}{int(a[2])} vs {b[1]}{int(b[2])}): they were not trained together; give encoder= of the same "
            "step")


def config_notes(cfg: Mapping[str, Mapping[str, Any]], defaults: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """``key=value`` of the config keys the tensors cannot show, ``(default: x)`` where the YAML differs from
    the official defaults: a wrong config with the right shapes still imports, so the summary prints these."""
    out = []
    for section, key in SHAPELESS:
        value, default = cfg.get(section, {}).get(key), defaults.get(section, {}).get(key)
        out.append(f"{section}.{key}={value!r}" + (f" (default: {default!r})" if value != default else ""))
    return out


def check_verified(diff: float, out: Path) -> None:
    """Refuse a reload whose eps differs from the converted network's (NaN included): remove what was written."""
    if not math.isfinite(diff) or diff != 0.0:
        out.unlink(missing_ok=True)
        raise UserError(f"out={out}: the written checkpoint reloads with max |eps difference| {diff:.1e}, not 0; "
                        "it was removed. Check the input files (copy them again) and report the difference")
