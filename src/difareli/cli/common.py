"""Small helpers shared by the thin Hydra entry points."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from difareli.cli import help as command_help
from difareli.configs import CONFIG_PATH, instantiate_group
from difareli.diffusion.spec import check_sampler
from difareli.runtime.core import Runtime

# Every Hydra command imports this module: the resolvers its --help template calls are registered here.
command_help.register()

__all__ = ["CONFIG_PATH", "check_relighting", "instantiate_group", "log_hyperparameters", "metric_value"]


def check_relighting(cfg: DictConfig) -> None:
    """How a command relights, checked before any work (the Relighter reads its checkpoint before it takes these):
    its ``sampler`` (:func:`~difareli.diffusion.spec.check_sampler`: by key, then whole) and its ``runtime`` (known
    keys and values)."""
    check_sampler(cfg.sampler)
    Runtime.from_config(cfg.runtime)


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
