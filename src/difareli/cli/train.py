"""difareli-train: compose the config, instantiate data + model + trainer, fit, return the optimized metric."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
import lightning as L
from omegaconf import DictConfig

from difareli import errors
from difareli.cli import common
from difareli.lit.checkpoint import read_checkpoint
from difareli.lit import logging as lit_logging


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit the configured model; returns the trainer, model, datamodule and the optimized metric."""
    if cfg.get("sample_grid"):
        errors.check_sampler(cfg.sampler)
    L.seed_everything(cfg.seed, workers=True)
    datamodule = hydra.utils.instantiate(cfg.data)
    ckpt_path = cfg.get("ckpt_path")
    # A resumed checkpoint is read once here (its statistics, the config check); Lightning then restores it.
    # ("last"/"best" are Lightning's names: no file to read here.)
    ckpt = read_checkpoint(ckpt_path) if ckpt_path and Path(ckpt_path).is_file() else None
    # The network's input sizes and the non-spatial statistics come from the data set (the training split),
    # or, when resuming, from the checkpoint: a resumed run keeps the normalisation it was trained with.
    model = hydra.utils.instantiate(cfg.model, input_dims=datamodule.input_dims(),
                                    nonspatial_stats=nonspatial_stats(datamodule, ckpt))
    trainer = hydra.utils.instantiate(
        cfg.trainer,
        callbacks=common.instantiate_group(cfg.get("callbacks")),
        logger=common.instantiate_group(cfg.get("logger")) or False,
    )
    common.log_hyperparameters(trainer, cfg)
    if ckpt_path:  # a mismatching config: list what differs, not a size-mismatch dump
        errors.check_resume(ckpt_path, model, ckpt)
    lit_logging.log_run_info(trainer, cfg)  # git commit + resolved config as text
    trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path)
    metric = common.metric_value(trainer.callback_metrics, cfg.get("optimized_metric"))
    return {"trainer": trainer, "model": model, "datamodule": datamodule, "metric": metric}


def nonspatial_stats(datamodule, ckpt: dict[str, Any] | None) -> dict[str, list[float]] | None:
    """Plain ``{mean, std}`` lists: from the checkpoint dict when resuming, else from the training split."""
    if ckpt is not None:
        return ckpt["hyper_parameters"].get("nonspatial_stats")
    mean, std = datamodule.nonspatial_stats()
    return {"mean": [float(v) for v in mean], "std": [float(v) for v in std]}


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="train")
@errors.cli_entry("train")
def main(cfg: DictConfig) -> float | None:
    return train(cfg)["metric"]


if __name__ == "__main__":
    main()
