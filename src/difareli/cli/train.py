"""difareli-train: compose the config, instantiate data + model + trainer, fit, return the optimized metric."""

from __future__ import annotations

import hydra
import lightning as L
from omegaconf import DictConfig

from difareli.cli import common


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="train")
def main(cfg: DictConfig) -> float | None:
    L.seed_everything(cfg.seed, workers=True)
    datamodule = hydra.utils.instantiate(cfg.data)
    model = hydra.utils.instantiate(cfg.model, input_dims=datamodule.input_dims())
    trainer = hydra.utils.instantiate(
        cfg.trainer, callbacks=common.instantiate_group(cfg.get("callbacks")),
        logger=common.instantiate_group(cfg.get("logger")) or False,
    )
    common.log_hyperparameters(trainer, cfg)
    trainer.fit(model, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
    if cfg.get("sample_grid") and not trainer.fast_dev_run:
        common.write_sample_grid(model, datamodule, cfg.sampler, trainer.default_root_dir)
    return common.metric_value(trainer.callback_metrics, cfg.get("optimized_metric"))


if __name__ == "__main__":
    main()
