"""Small helpers shared by the thin Hydra entry points."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

#: The repository's conf/ folder (editable install). Absolute: Hydra resolves a relative config_path against
#: the calling *module* when started from a console script, which would look for a `conf` package.
CONFIG_PATH = str(Path(__file__).resolve().parents[3] / "conf")


def instantiate_group(group: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` entry of a config group (callbacks, loggers); ``None`` -> ``[]``."""
    if not group:
        return []
    return [hydra.utils.instantiate(c) for c in group.values() if isinstance(c, DictConfig) and "_target_" in c]


def log_hyperparameters(trainer, cfg: DictConfig) -> None:
    """Send the resolved config to every logger (Hydra also saves it under <run>/.hydra/config.yaml)."""
    flat = OmegaConf.to_container(cfg, resolve=True)
    for logger in trainer.loggers:
        logger.log_hyperparams(flat)


def metric_value(metrics: dict, name: str | None) -> float | None:
    """The optimized metric for Hydra sweepers, or None when absent (e.g. fast_dev_run)."""
    if not name or name not in metrics:
        return None
    return float(metrics[name])
