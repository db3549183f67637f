"""Small helpers shared by the thin Hydra entry points."""

from __future__ import annotations


from omegaconf import DictConfig, OmegaConf

from difareli.diffusion.spec import check_sampler
from difareli import errors
from difareli.checkpoints import zoo
from difareli.render.sun_fit import check_target_sun
from difareli.configs import CONFIG_PATH, instantiate_group

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


#: The longest rotation video the relight and video commands make.
MAX_FRAMES = 3600


def validate_relight(cfg: DictConfig, *, frames: tuple[str, object, int], fps: tuple[str, object],
                     envmap: tuple[str, object]) -> None:
    """The checks every relighting command (relight, video) makes before any work: sampler, checkpoint (a file
    or a shipped name), batch size, output folder, target shadow strength, and its frame count / rate / env map
    where target maps are marched, under the command's own keys (``(key, value[, minimum])``)."""
    check_sampler(cfg.sampler)
    zoo.resolve(cfg.checkpoint, "checkpoint")
    errors.check_int(cfg.batch_size, "batch_size", 1)
    errors.check_out_dir(cfg.out_dir)
    errors.check_number(cfg.target.shadow, "target.shadow")
    check_target_sun(cfg.target.sun, "target.sun")
    key, value, minimum = frames
    errors.check_int(value, key, minimum)
    if value > MAX_FRAMES:  # 60 frames x 60 s: anything longer is a typo, and it would fill the disk first
        raise errors.UserError(f"{key}={value} is invalid: at most {MAX_FRAMES} frames (a {MAX_FRAMES // 20}-s video "
                               f"at 20 fps); e.g. {key}=60")
    errors.check_int(fps[1], fps[0], 1)
    if envmap[1] is not None:
        errors.check_file(envmap[1], envmap[0])
