"""difareli-train: compose the config, instantiate data + model + trainer, fit, return the optimized metric."""

from __future__ import annotations

from typing import Any

import hydra
import lightning as L
from omegaconf import DictConfig

from difareli.cli import common
from difareli.lit import logging as lit_logging


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit the configured model; returns the trainer, model, datamodule and the optimized metric."""
    L.seed_everything(cfg.seed, workers=True)
    datamodule = hydra.utils.instantiate(cfg.data)
    # The network's input sizes come from the data set (which encodings, how many channels).
    model = hydra.utils.instantiate(cfg.model, input_dims=datamodule.input_dims())
    trainer = hydra.utils.instantiate(
        cfg.trainer,
        callbacks=common.instantiate_group(cfg.get("callbacks")),
        logger=common.instantiate_group(cfg.get("logger")) or False,
    )
    common.log_hyperparameters(trainer, cfg)
    lit_logging.log_run_info(trainer, cfg)  # git commit + resolved config as text
    trainer.fit(model, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
    if cfg.get("sample_grid") and not trainer.fast_dev_run and trainer.is_global_zero:
        lit_logging.log_image(trainer, "samples/grid",
                              common.write_sample_grid(model, datamodule, cfg.sampler, trainer.default_root_dir))
    metric = common.metric_value(trainer.callback_metrics, cfg.get("optimized_metric"))
    return {"trainer": trainer, "model": model, "datamodule": datamodule, "metric": metric}


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="train")
def main(cfg: DictConfig) -> float | None:
    return train(cfg)["metric"]


if __name__ == "__main__":
    main()
