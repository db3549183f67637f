"""Reference checkpoints shipped with the package, loadable by name (``checkpoint=difareli_pp-synth64``).

Each one is ``src/difareli/checkpoints/<name>.ckpt`` (a slim Lightning checkpoint: the EMA weights, the plain
hyperparameters, the module class; no optimizer state; kept for resuming training and ``init_from``) beside its model
card ``<name>.md`` and its weights folder ``<name>/`` (``model.safetensors``, ``config.json``, ``README.md``, written
by ``difareli-export``: loads with no pickle). :func:`export` writes the .ckpt and card from a training run;
:func:`difareli.checkpoints.loading.resolve` turns a name or a path into a file or folder, and every loader goes
through it: ``load_checkpoint`` reads a shipped name from its folder.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from difareli.checkpoints.format import SLIM_KEYS, is_folder, load_torch_file
from difareli.errors import UserError
from difareli.utils.fileio import torch_save_atomic, write_text_atomic

if TYPE_CHECKING:
    import torch

#: Where the shipped checkpoints and their model cards live (package data).
SHIPPED_DIR = Path(__file__).resolve().parent  # the weights ship beside this module
#: The shipped model that wins where a user relights (suite.md's first table): the app's, the demo's and the photo
#: benches' default (conf/app.yaml and conf/demo.yaml name it too; tests/checkpoints/test_zoo.py holds them equal).
RECOMMENDED = "difareli_pp_ss_est-synth64"


def available() -> list[str]:
    """Names of the shipped checkpoints."""
    folders = {p.name for p in SHIPPED_DIR.iterdir() if is_folder(p)}
    return sorted({p.stem for p in SHIPPED_DIR.glob("*.ckpt")} | folders)


def suite() -> str | None:
    """The reference suite (every shipped model beside identity and the Lambertian ratio image on a store of an
    unseen seed, written by ``scripts/reference_suite.py --ship``), or None when it is not shipped."""
    path = SHIPPED_DIR / "suite.md"
    return path.read_text() if path.is_file() else None


def card(name: str) -> str:
    """The model card (Markdown) of a shipped checkpoint."""
    path = SHIPPED_DIR / f"{name}.md"
    if not path.is_file():
        raise UserError(f"no model card for {name!r}; shipped: {available()}")
    return path.read_text()


def slim(ckpt: Mapping[str, Any], dtype: torch.dtype | None = None) -> dict[str, Any]:
    """A Lightning checkpoint reduced to what inference needs; ``dtype`` (e.g. bf16) casts floating weights."""
    out = {k: ckpt[k] for k in SLIM_KEYS if k in ckpt}
    state = {}
    for key, value in ckpt["state_dict"].items():
        if key.startswith("_orig_mod.") or ".n_averaged" in key:
            continue
        state[key] = value.to(dtype) if dtype is not None and value.is_floating_point() else value
    out["state_dict"] = state
    return out


def export(run_checkpoint: str | Path, name: str, facts: Mapping[str, Any], *, out_dir: str | Path | None = None,
           dtype: torch.dtype | None = None) -> tuple[Path, Path]:
    """Write ``<name>.ckpt`` (slim, loads with ``weights_only=True``) and its model card ``<name>.md``.

    ``facts`` fill the card: data, seed, preset, steps, wall time and hardware, precision, benchmark rows
    (Markdown), anything else as ``key: value`` lines. Written atomically (temporary file, then rename).
    """
    out = Path(out_dir) if out_dir is not None else SHIPPED_DIR
    out.mkdir(parents=True, exist_ok=True)
    ckpt = load_torch_file(Path(run_checkpoint), "checkpoint")
    small = slim(ckpt, dtype)
    small["model_card"] = {k: v for k, v in facts.items() if isinstance(v, (str, int, float, bool))}
    target = torch_save_atomic(small, out / f"{name}.ckpt")
    md = write_text_atomic(out / f"{name}.md", model_card(name, small, facts))
    return target, md


def model_card(name: str, ckpt: Mapping[str, Any], facts: Mapping[str, Any]) -> str:
    """The Markdown model card of a slim checkpoint."""
    hp = ckpt["hyper_parameters"]
    n_params = sum(v.numel() for v in ckpt["state_dict"].values())
    lines = [f"# {name}", "", facts.get("summary", ""), "",
             f"Load: `difareli.lit.load_checkpoint(\"{name}\")`, or `checkpoint={name}` in any CLI.", "",
             "| field | value |", "|---|---|",
             f"| model | {hp.get('name')} ({ckpt.get('difareli_module')}) |",
             f"| preset | {hp.get('preset')}, {n_params / 1e6:.2f} M parameters |",
             f"| spatial inputs | {', '.join(hp.get('spatial_inputs') or []) or '-'} |",
             f"| non-spatial inputs | {', '.join(hp.get('nonspatial_inputs') or []) or '-'} |",
             f"| steps | {facts.get('steps') or ckpt.get('global_step')} |"]  # a fine-tune states its start
    for key in ("data", "seed", "batch_size", "optimizer", "precision", "hardware", "wall_time", "weights",
                "sampler"):
        if key in facts:
            lines.append(f"| {key.replace('_', ' ')} | {facts[key]} |")
    lines += ["", "## Benchmark", "", str(facts.get("benchmark", "(not measured)")), "",
              "## Intended use", "", str(facts.get("intended_use", "")), "",
              "## Licence of the training data", "", str(facts.get("licence", "")), ""]
    if facts.get("notes"):
        lines += ["## Notes", "", str(facts["notes"]), ""]
    lines += ["## Training config", "", "```json", json.dumps(hp, indent=1, sort_keys=True, default=str), "```", ""]
    return "\n".join(lines)
