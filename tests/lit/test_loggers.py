"""Rich logging (difareli.lit.logging): images, tables, config and git commit reach TensorBoard and wandb
(offline), read back from what the loggers wrote; and a training run logs its grids and curves."""

from __future__ import annotations

import io
import json
import subprocess
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from omegaconf import OmegaConf

from difareli.evaluation import tables
from difareli.lit import logging as lit_logging

from tests.helpers import compose_train

REPO = Path(__file__).resolve().parents[2]


def _events(log_dir: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(str(log_dir), size_guidance={"images": 0, "tensors": 0, "scalars": 0})
    ea.Reload()
    return ea


def _text(ea, tag: str) -> str:
    return ea.Tensors(f"{tag}/text_summary")[-1].tensor_proto.string_val[0].decode()


def _table() -> tables.Table:
    recs = [tables.Record("lambertian", p, f"r{i}", 0.1 + i, 0.01 * i, 0.2, 1.0) for p in ("same", "different")
            for i in range(3)]
    return tables.summarize(recs)


def _image() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (24, 40, 3), dtype=np.uint8)


def test_tensorboard_gets_images_tables_config_and_commit(tmp_path):
    from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

    tb = TensorBoardLogger(tmp_path / "tb", name=None, version="", default_hp_metric=False)
    loggers = [tb, CSVLogger(tmp_path / "csv")]  # the CSV logger has neither capability: skipped, no error
    img = _image()
    iio.imwrite(tmp_path / "grid.png", img)
    lit_logging.log_image(loggers, "val/grid", tmp_path / "grid.png", step=7)
    lit_logging.log_table(loggers, "benchmark/summary", _table(), step=0)
    info = lit_logging.log_run_info(loggers, OmegaConf.create({"model": {"lr": 1e-4}, "seed": 42}))
    ea = _events(tmp_path / "tb")
    ev = ea.Images("val/grid")[0]
    assert ev.step == 7 and (ev.height, ev.width) == (24, 40)
    assert np.array_equal(iio.imread(io.BytesIO(ev.encoded_image_string)), img)  # lossless round trip
    assert "| lambertian |" in _text(ea, "benchmark/summary")
    # "unknown" outside a git checkout (e.g. an sdist): the log still says so.
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    head = head or "unknown"
    assert info["git_commit"] == head
    config = _text(ea, "config")
    assert f"git commit {head}" in config and "lr: 0.0001" in config


def test_wandb_offline_gets_image_and_table(tmp_path, monkeypatch):
    from lightning.pytorch.loggers import WandbLogger

    monkeypatch.setenv("WANDB_SILENT", "true")
    lg = WandbLogger(save_dir=str(tmp_path), offline=True, project="difareli-test", name="t")
    img = _image()
    lit_logging.log_image([lg], "val/grid", img, step=1)
    lit_logging.log_table([lg], "benchmark/summary", _table(), step=1)
    lit_logging.log_run_info([lg], OmegaConf.create({"seed": 42}))
    run_dir = Path(lg.experiment.dir).parent
    assert lg.experiment.config["git_commit"] == lit_logging.git_commit()["git_commit"]
    lg.experiment.finish()
    assert run_dir.name.startswith("offline-run-") and list(run_dir.glob("*.wandb"))
    pngs = list((run_dir / "files" / "media" / "images").rglob("*.png"))
    assert len(pngs) == 1 and np.array_equal(iio.imread(pngs[0])[..., :3], img)
    table = json.loads(next((run_dir / "files" / "media" / "table").rglob("summary_*.table.json")).read_text())
    assert table["columns"][0] == "method" and table["data"][0][0] == "lambertian"


@pytest.mark.slow  # a 2-step training with grids and samples: ~15 s CPU, ~60-80 s wall on the loaded 2-core CI
def test_training_logs_grids_loss_curve_samples_and_config(synth_store, tmp_path):
    from difareli.cli.train import train

    cfg = compose_train(tmp_path, [f"data.root={synth_store}", "data.resolution=32", "data.synth=null",
                                   "data.num_workers=0", "data.batch_size=4", "model.preset=tiny", "trainer=cpu",
                                   "trainer.max_steps=2", "trainer.val_check_interval=2", "trainer.limit_val_batches=1",
                                   "trainer.log_every_n_steps=1",
                                   "callbacks.loss_curve.every_n_steps=1", "callbacks.reconstruction_grid.num_images=2",
                                   "sampler.steps=2", "logger=tensorboard", "~callbacks.progress_bar"])
    train(cfg)
    ea = _events(tmp_path / "tensorboard")
    assert {"val/reconstruction_grid", "train/loss_curve", "samples/grid"} <= set(ea.Tags()["images"])
    assert {"train/loss", "val/loss"} <= set(ea.Tags()["scalars"])
    grid = iio.imread(io.BytesIO(ea.Images("samples/grid")[0].encoded_image_string))
    assert np.array_equal(grid, iio.imread(tmp_path / "sample_grid.png")[..., :3])
    assert "git commit" in _text(ea, "config") and "preset: tiny" in _text(ea, "config")


def test_benchmark_logs_summary_table_and_comparisons(synth_store, tmp_path):
    from difareli.cli.benchmark import run

    cfg = compose_train(tmp_path, [f"store={synth_store}", "progress=false", "num_threads=null", "method=identity",
                                   "limit=2", "grid_pairs=1", "save_images=false", "logger=tensorboard"],
                        config_name="benchmark")
    result = run(cfg)
    ea = _events(tmp_path / "tensorboard")
    assert set(ea.Tags()["images"]) == {"benchmark/comparison_same_subject", "benchmark/comparison_different_subject"}
    assert _text(ea, "benchmark/summary") == result.table.to_markdown(digits=4)
    assert ("_target_: difareli.evaluation.baselines.Identity" in _text(ea, "config")
            and "git commit" in _text(ea, "config"))
