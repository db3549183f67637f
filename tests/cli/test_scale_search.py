"""hparams_search=optuna: a 3-trial TPE sweep through the real CLI returns each trial's val/loss to Optuna."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]


def _last_val_loss(trial_dir: Path) -> float:
    rows = list(csv.DictReader(open(trial_dir / "csv" / "metrics.csv")))
    return float([r for r in rows if r.get("val/loss")][-1]["val/loss"])


@pytest.mark.slow  # one interpreter, three 2-step trainings: ~25 s idle, ~1-2 min on the loaded 2-core CI
def test_optuna_three_trials_minimise_val_loss(synth_store, tmp_path):
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "difareli.cli.train", "hparams_search=optuna", "hydra.sweeper.n_trials=3",
           "hydra.sweeper.sampler.n_startup_trials=2", f"hydra.sweep.dir={sweep}", f"paths.log_dir={tmp_path}",
           f"data.root={synth_store}", "data.resolution=32", "data.synth=null", "data.num_workers=0",
           "model.preset=tiny", "trainer=cpu", "sample_grid=false", "trainer.max_steps=2",
           "trainer.val_check_interval=2", "trainer.limit_val_batches=1", "~callbacks.progress_bar",
           "~callbacks.reconstruction_grid"]
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    print(f"optuna 3 trials: {time.perf_counter() - t0:.1f} s wall")
    assert proc.returncode == 0, proc.stderr[-4000:]
    trials = sorted(p for p in sweep.iterdir() if p.is_dir() and p.name.isdigit())
    assert [p.name for p in trials] == ["0", "1", "2"]
    losses = [_last_val_loss(p) for p in trials]
    result = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    # The sweeper got each trial's float and kept the smallest.
    assert result["name"] == "optuna" and result["best_value"] == pytest.approx(min(losses), rel=1e-6)
    for p in trials:
        over = dict(o.split("=", 1) for o in yaml.safe_load((p / ".hydra" / "overrides.yaml").read_text()))
        assert 1e-5 <= float(over["model.optimizer.lr"]) <= 1e-3
        assert int(over["data.batch_size"]) in (8, 16, 32)
        assert float(over["callbacks.ema.decay"]) in (0.999, 0.9995, 0.9999)
    best = losses.index(min(losses))
    best_over = dict(o.split("=", 1) for o in yaml.safe_load((trials[best] / ".hydra" / "overrides.yaml").read_text()))
    assert float(result["best_params"]["model.optimizer.lr"]) == pytest.approx(float(best_over["model.optimizer.lr"]))
