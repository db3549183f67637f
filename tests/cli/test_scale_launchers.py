"""Launchers and scale-out configs: every key checked against the installed plugins' dataclasses and
Lightning's classes; a 2-job multirun through submitit's local executor."""

from __future__ import annotations

import dataclasses
import os
import pickle
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from difareli.configs import CONFIG_DIR

REPO = Path(__file__).resolve().parents[2]
CONF = CONFIG_DIR


def _compose(overrides: list[str]):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Hydra's note that same-named yaml files are matched to the schema
        with initialize_config_dir(str(CONF), version_base="1.3"):
            return compose("train", overrides=overrides, return_hydra_config=True)


@pytest.mark.parametrize("name, schema", [("submitit_slurm", "SlurmQueueConf"), ("submitit_local", "LocalQueueConf")])
def test_launcher_yaml_keys_are_plugin_fields(name, schema):
    from hydra_plugins.hydra_submitit_launcher import config as plugin

    cls = getattr(plugin, schema)
    ours = OmegaConf.load(CONF / "hydra" / "launcher" / f"{name}.yaml")
    fields = {f.name for f in dataclasses.fields(cls)}
    assert set(ours) <= fields, set(ours) - fields
    assert ours._target_ == cls._target_  # the same launcher class the plugin registers
    OmegaConf.merge(OmegaConf.structured(cls), ours)  # types match the plugin's (raises otherwise)


def test_slurm_launcher_follows_trainer_devices_and_requeue_plugin():
    from lightning.pytorch.plugins.environments import SLURMEnvironment
    from hydra.utils import instantiate

    cfg = _compose(["hydra/launcher=submitit_slurm", "trainer=ddp_slurm", "trainer.devices=4", "trainer.num_nodes=2",
                    "hydra.launcher.partition=gpu"])
    launcher = cfg.hydra.launcher
    assert (launcher.tasks_per_node, launcher.gpus_per_node, launcher.nodes) == (4, 4, 2)
    assert launcher.partition == "gpu" and launcher.signal_delay_s > 0 and launcher.array_parallelism == 32
    plugins = [instantiate(p) for p in cfg.trainer.plugins]
    env = next(p for p in plugins if isinstance(p, SLURMEnvironment))
    assert env.auto_requeue and type(plugins[0]).__name__ == "AtomicCheckpointIO"  # checkpoints stay atomic
    assert cfg.trainer.strategy == "ddp" and cfg.trainer.accelerator == "gpu"


def test_trainer_configs_build_their_strategies():
    import lightning as L
    from hydra.utils import instantiate
    from lightning.pytorch.strategies import DDPStrategy, FSDPStrategy

    cfg = _compose(["trainer=ddp_cpu"])
    trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False, default_root_dir="/tmp")
    assert isinstance(trainer.strategy, DDPStrategy) and trainer.num_devices == 2
    assert trainer.strategy._get_process_group_backend() == "gloo"
    fsdp = instantiate(_compose(["trainer=fsdp"]).trainer.strategy)
    assert isinstance(fsdp, FSDPStrategy) and fsdp._state_dict_type == "full"
    assert isinstance(L.Trainer, type)


def test_optuna_search_space_composes():
    cfg = _compose(["hparams_search=optuna"])
    sw = cfg.hydra.sweeper
    assert sw._target_.endswith("OptunaSweeper") and sw.direction == "minimize"
    assert sw.sampler._target_ == "optuna.samplers.TPESampler"
    assert set(sw.params) == {"model.optimizer.lr", "data.batch_size", "callbacks.ema.decay"}
    assert cfg.optimized_metric == "val/loss" and "lr" in cfg.model.optimizer and "decay" in cfg.callbacks.ema


@pytest.mark.slow  # three interpreters (the sweep + 2 submitit jobs): ~30 s idle, ~80 s on the loaded 2-core CI
def test_submitit_local_two_job_multirun(synth_store, tmp_path):
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "difareli.cli.train", "-m", "hydra/launcher=submitit_local",
           "model=difareli,difareli_pp", "debug=fdr", f"data.root={synth_store}", "data.resolution=32",
           "data.synth=null", "data.num_workers=0", "data.batch_size=4", "model.preset=tiny", "trainer=cpu",
           f"hydra.sweep.dir={sweep}", f"paths.log_dir={tmp_path}"]
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    print(f"submitit_local 2 jobs: {time.perf_counter() - t0:.1f} s wall")
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "Submitit 'local' sweep output dir" in proc.stdout + proc.stderr
    for job in ("0", "1"):
        assert (sweep / job / ".hydra" / "config.yaml").is_file()
    # Each job ran in its own submitit process and reported success back to the launcher.
    results = sorted((sweep / ".submitit").glob("*/*_result.pkl"))
    assert len(results) == 2
    models = set()
    for r in results:
        status, ret = pickle.loads(r.read_bytes())
        assert status == "success", ret
        models.add(ret.cfg.model.name)
        assert int(r.name.split("_")[0]) != os.getpid()
    assert models == {"difareli", "difareli_pp"}
