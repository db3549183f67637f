"""Where the package's Hydra configs live, and plain-YAML reads of them for callers without Hydra.

The configs live at the top of the repository (``conf/``, the lightning-hydra-template layout) and are installed as
the package ``difareli.conf`` (setup.py maps it), found through Hydra's package search path
(``pkg://difareli.conf``), so every console script works wherever the package is installed. A ``conf/`` folder in
the directory a command is run from is searched too (``hydra.searchpath`` in each primary config): a user's own
groups and options (``conf/local/default.yaml`` for machine settings, ``conf/model/my_variant.yaml``) extend the
shipped ones without touching the installation.
"""

from __future__ import annotations

import os
import secrets
from datetime import datetime
from importlib import resources
from pathlib import Path
from typing import Any

from difareli.errors import MissingError

#: The shipped config folder (a real folder: the checkout's conf/ in an editable install, package data in a wheel).
CONFIG_DIR = Path(str(resources.files("difareli.conf")))
#: What ``@hydra.main(config_path=...)`` is given.
CONFIG_PATH = "pkg://difareli.conf"


def train_precision() -> str:
    """``${difareli_precision:}`` in a trainer config: ``bf16-mixed`` where this CPU has native bf16 arithmetic
    (``avx512_bf16`` / ``amx_bf16``, :func:`difareli.hardware.auto_precision`), else ``32-true``. Without it bf16 is
    emulated: on an AVX2-only EPYC one 3x3 convolution (16x64x64x64, forward + backward) took 29.4 s in bf16
    autocast against 0.91 s in fp32, and a bf16 recipe trained at 0.02 it/s."""
    from difareli.hardware import auto_precision

    return "bf16-mixed" if auto_precision("cpu") == "bf16" else "32-true"


def run_stamp(pattern: str = "%Y-%m-%d_%H-%M-%S") -> str:
    """``${difareli_run:}``: a run folder's name, the start time plus this process's id and 4 random hex digits.
    ``${now:}`` alone let two commands started in the same second share (and overwrite) one folder; the id keeps
    them apart on one machine, the random digits across the nodes of a cluster writing to one log folder. Hydra
    caches the value per config (``use_cache``) and copies that cache into every job of a sweep, so one run (or
    one multirun) sees one name; each new composition draws a new one."""
    return f"{datetime.now().strftime(pattern)}_{os.getpid()}-{secrets.token_hex(2)}"


def _register_resolvers() -> None:
    # Only where OmegaConf is installed: the GPU readiness script reads plain YAML on images without Hydra.
    try:
        from omegaconf import OmegaConf
    except ImportError:
        return
    OmegaConf.register_new_resolver("difareli_precision", train_precision, replace=True)
    # paths.root_dir: the directory the command runs in (jobs never chdir). Not ${hydra:runtime.cwd}: a multirun's
    # sweeper resolves hydra.sweep.dir (under paths.log_dir) before any job has a HydraConfig, and that failed.
    OmegaConf.register_new_resolver("difareli_cwd", os.getcwd, replace=True)
    OmegaConf.register_new_resolver("difareli_run", run_stamp, replace=True, use_cache=True)


_register_resolvers()


def config_file(group: str, name: str) -> Path:
    """``conf/<group>/<name>.yaml``, or a KeyError listing the group's options."""
    path = CONFIG_DIR / group / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise MissingError(f"no config {group}/{name}.yaml; known {group} options: {known}")
    return path


def read_yaml(group: str, name: str) -> dict[str, Any]:
    """One shipped config as a plain mapping (no Hydra composition, no interpolation)."""
    import yaml

    return yaml.safe_load(config_file(group, name).read_text()) or {}


def instantiate_group(group) -> list[Any]:
    """Instantiate every ``_target_`` entry of a config group (callbacks, loggers); ``None`` -> ``[]``."""
    import hydra
    from omegaconf import DictConfig

    if not group:
        return []
    return [hydra.utils.instantiate(c) for c in group.values() if isinstance(c, DictConfig) and "_target_" in c]
