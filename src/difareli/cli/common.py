"""Small helpers shared by the thin Hydra entry points."""

from __future__ import annotations


from omegaconf import DictConfig, OmegaConf

from difareli.diffusion.spec import check_sampler
from difareli import errors
from difareli.configs import CONFIG_PATH, instantiate_group
from difareli.utils.video import video_format

__all__ = ["CONFIG_PATH", "instantiate_group", "log_hyperparameters", "metric_value", "validate_relight"]


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


def validate_relight(cfg: DictConfig, *, fps: tuple[str, object], fmt: tuple[str, object]) -> None:
    """The checks every relighting command (relight, video) makes of its own values before any work: the video
    format, the sampler, batch size, output folder and frame rate, under the command's own keys (``(key, value)``).
    The checkpoint is checked where it is loaded (:class:`~difareli.relight.relighter.Relighter`), the request's
    values by the request (:meth:`~difareli.relight.request.Request.from_config`)."""
    video_format(fmt[1], fmt[0])
    check_sampler(cfg.sampler)
    errors.check_int(cfg.batch_size, "batch_size", 1)
    errors.check_out_dir(cfg.out_dir)
    errors.check_int(fps[1], fps[0], 1)
