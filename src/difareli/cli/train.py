"""difareli-train: compose the config, instantiate data + model + trainer, fit, return the optimized metric."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
import lightning as L
from omegaconf import DictConfig

from difareli.diffusion.spec import check_sampler
from difareli import errors
from difareli.checkpoints import loading
from difareli.cli import common
from difareli.checkpoints.loading import check_resume, read_checkpoint
from difareli.lit import logging as lit_logging
from difareli.lit import summary as lit_summary


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit the configured model; returns the trainer, model, datamodule and the optimized metric."""
    if cfg.get("sample_grid"):
        check_sampler(cfg.sampler)
    check_accelerator(cfg.trainer)
    L.seed_everything(cfg.seed, workers=True)
    datamodule = hydra.utils.instantiate(cfg.data)
    ckpt_path = cfg.get("ckpt_path")
    # A resumed checkpoint is read once here (its statistics, the config check); Lightning then restores it.
    # ("last"/"best" are Lightning's names: no file to read here.)
    ckpt = read_checkpoint(ckpt_path) if ckpt_path and Path(ckpt_path).is_file() else None
    init_from = cfg.get("init_from")
    if init_from and ckpt_path:
        raise errors.UserError(f"init_from={init_from} and ckpt_path={ckpt_path}: give one (ckpt_path resumes a run "
                               "with its optimizer and step; init_from starts a new run from a checkpoint's weights)")
    if init_from:  # fine-tuning: the weights (and their input normalisation), not the optimizer or the step
        ckpt = read_checkpoint(str(loading.resolve(init_from, "init_from")))
    if ckpt is not None:  # another variant's statistics would not even fit the network: name both variants
        check_resume_variant(ckpt_path or init_from, ckpt, cfg.model, "init_from" if init_from else "ckpt_path")
        datamodule.check_checkpoint(ckpt["hyper_parameters"], ckpt_path or init_from)  # before a size mismatch
    # The network's input sizes and the non-spatial statistics come from the data set (the training split),
    # or, when resuming, from the checkpoint: a resumed run keeps the normalisation it was trained with.
    # The maker of the shadow maps it trains on is recorded, so a relight can say when its target maps differ.
    maps = datamodule.shadow_map_maker() if "shadow_map" in list(cfg.model.get("spatial_inputs") or []) else None
    model = hydra.utils.instantiate(cfg.model, input_dims=datamodule.input_dims(),
                                    nonspatial_stats=nonspatial_stats(datamodule, ckpt), training_maps=maps)
    trainer = hydra.utils.instantiate(
        cfg.trainer,
        callbacks=common.instantiate_group(cfg.get("callbacks")),
        logger=common.instantiate_group(cfg.get("logger")) or False,
    )
    common.log_hyperparameters(trainer, cfg)
    if ckpt_path or init_from:  # a mismatching config: list what differs, not a size-mismatch dump
        check_resume(ckpt_path or init_from, model, ckpt)
    if init_from:
        model.load_state_dict(ckpt["state_dict"])
    lit_logging.log_run_info(trainer, cfg)  # git commit + resolved config as text
    try:
        trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path)
    except SystemExit:  # Lightning ends a Ctrl-C'd fit with sys.exit(1): say where the run got to first
        if trainer.interrupted:
            report(trainer, cfg)
        raise
    report(trainer, cfg)
    metric = common.metric_value(trainer.callback_metrics, cfg.get("optimized_metric"))
    return {"trainer": trainer, "model": model, "datamodule": datamodule, "metric": metric}


def report(trainer, cfg: DictConfig) -> None:
    """The closing line: steps done of planned, why it stopped, the checkpoint, the next command."""
    from hydra.core.hydra_config import HydraConfig

    overrides = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    if trainer.is_global_zero:
        print(lit_summary.train_summary(trainer, overrides, cfg.data.get("root"), cfg.get("ckpt_path")), flush=True)


def check_accelerator(trainer_cfg: DictConfig) -> None:
    """``trainer=gpu`` (accelerator gpu/cuda) on a machine without a CUDA device: one line, not Lightning's trace."""
    import torch

    acc = str(trainer_cfg.get("accelerator", "auto")).lower()
    if acc in ("gpu", "cuda") and not torch.cuda.is_available():
        build = "a CPU build" if torch.version.cuda is None else f"CUDA {torch.version.cuda}, but no device is visible"
        raise errors.UserError(f"trainer.accelerator={acc} but this machine has no usable CUDA GPU (torch "
                               f"{torch.__version__}: {build}); use trainer=cpu (or trainer=default, which picks "
                               "what is there)")


def check_resume_variant(ckpt_path: Any, ckpt: dict[str, Any], model_cfg: DictConfig, key: str = "ckpt_path") -> None:
    """Resuming (or initialising, ``key="init_from"``) into another model variant (other name or inputs) is
    refused naming both variants."""
    hp = ckpt.get("hyper_parameters") or {}
    keys = ("name", "spatial_inputs", "nonspatial_inputs")
    saved = {k: hp.get(k) for k in keys}
    now = {k: (list(model_cfg.get(k)) if k != "name" and model_cfg.get(k) is not None else model_cfg.get(k))
           for k in keys}
    saved = {k: list(v) if isinstance(v, (list, tuple)) else v for k, v in saved.items()}
    diff = [f"{k}: checkpoint {saved[k]!r}, config {now[k]!r}" for k in keys if saved[k] != now[k]]
    if diff:
        raise errors.UserError(f"{key}={ckpt_path} was trained as model variant {saved['name']!r}, this run "
                               f"composes {now['name']!r} ({'; '.join(diff)}); "
                               f"{'resume' if key == 'ckpt_path' else 'start'} with model=<the variant it was "
                               "trained with> (its <run>/.hydra/config.yaml or model card says which)")


def nonspatial_stats(datamodule, ckpt: dict[str, Any] | None) -> dict[str, list[float]] | None:
    """Plain ``{mean, std}`` lists: from the checkpoint dict when resuming or initialising from one (the weights
    were trained with its normalisation), else from the training split."""
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
