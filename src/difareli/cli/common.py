"""Small helpers shared by the thin Hydra entry points."""

from __future__ import annotations


from omegaconf import DictConfig, OmegaConf

from difareli.configs import CONFIG_PATH, instantiate_group

__all__ = ["CONFIG_PATH", "instantiate_group", "log_hyperparameters", "metric_value"]


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
