"""The ``difareli-synth`` command that regenerates a SynthFaces store, read back from the store's header.

A store records every choice that defines its data (``SynthConfig.header_meta``), so a report that cites a store
can print the command that remakes it instead of relying on the caller to pass it along. The command names the
size and seed, the realism preset and the inputs, and any other key only where it differs from the CLI default.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from difareli.data.store import EncodingStore
from difareli.synth.effects import REALISM_PRESETS
from difareli.synth.config import auto_estimation_resolution
from difareli.errors import UserError

#: Always written, in this order (a reader compares stores by these first).
_ALWAYS = ("subjects", "lights", "resolution", "seed", "realism", "inputs")
#: Written where the header differs from the CLI's default.
_IF_CHANGED = ("light_group_size", "shading_region", "cam_jitter", "shadow_visible", "c_quantile")


def _cli_defaults() -> dict[str, Any]:
    """conf/synth.yaml, as ``difareli-synth`` starts from it (package data)."""
    return yaml.safe_load((resources.files("difareli.conf") / "synth.yaml").read_text())


def synth_command(store_dir: str | Path, meta: dict[str, Any] | None = None) -> str:
    """``difareli-synth out_dir=<store_dir> ...`` that regenerates the store (its header's ``meta`` if not given).

    Raises ValueError when the store was not made by ``difareli-synth`` (e.g. ``difareli-multipie``) or by a
    version of it that did not record its settings.
    """
    if meta is None:
        meta = EncodingStore.open(store_dir).store_meta
    if meta.get("generator") != "synthfaces" or meta.get("synthfaces_version") is None:
        raise UserError(f"{store_dir}: the store header names no difareli-synth settings (generator "
                        f"{meta.get('generator')!r}, version {meta.get('synthfaces_version')!r}); state its "
                        "command yourself")
    default = _cli_defaults()
    words = [f"out_dir={store_dir}"] + [f"{k}={meta[k]}" for k in _ALWAYS]
    words += [f"{k}={meta[k]}" for k in _IF_CHANGED if k in meta and meta[k] != default[k]]
    preset = REALISM_PRESETS[meta["realism"]]
    words += [f"effects.{k}={str(v).lower()}" for k, v in sorted(meta.get("effects", {}).items()) if preset.get(k) != v]
    # The header stores estimation_resolution resolved: name it only where it is not what 0 (auto) resolves to.
    r = int(meta.get("estimation_resolution", 0))
    if meta["inputs"] == "estimated" and r != auto_estimation_resolution(meta["resolution"]):
        words.append(f"estimation_resolution={r}")
    splits = {k: float(v) for k, v in meta.get("splits", {}).items()}
    if splits and splits != {k: float(v) for k, v in default["splits"].items()}:
        words += [f"splits.{k}={v:g}" for k, v in splits.items()]
    return "difareli-synth " + " ".join(words)
