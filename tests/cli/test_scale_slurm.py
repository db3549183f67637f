"""trainer=ddp_slurm without a cluster: SLURM's variables and a fake `scontrol` on PATH. A preemption signal
(SIGUSR1) makes Lightning's SLURMEnvironment(auto_requeue) save an hpc checkpoint and requeue the job id; the
requeued job (the same command again) resumes from that checkpoint by itself."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import lightning as L
import pytest
import torch

REPO = Path(__file__).resolve().parents[2]


class Preempt(L.Callback):
    """Sends SIGUSR1 to this process after ``at_step`` steps (what SLURM does before a preemption or the time
    limit), then stops as SLURM's kill would."""

    def __init__(self, at_step: int = 3):
        self.at_step = at_step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if trainer.global_step == self.at_step:
            os.kill(os.getpid(), signal.SIGUSR1)
            trainer.should_stop = True


@pytest.mark.slow  # two training processes: ~30 s idle, ~1-2 min on the loaded 2-core CI
def test_preempted_slurm_job_requeues_and_resumes(synth_store, tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    log = tmp_path / "scontrol.log"
    (bin_dir / "scontrol").write_text(f'#!/bin/sh\necho "$@" >> {log}\n')
    (bin_dir / "scontrol").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
           "PYTHONPATH": os.pathsep.join([str(REPO / "src"), str(REPO)]), "OMP_NUM_THREADS": "1",
           "PYTHONWARNINGS": "ignore", "SLURM_JOB_ID": "4242", "SLURM_JOB_NAME": "difareli", "SLURM_NTASKS": "1",
           "SLURM_NTASKS_PER_NODE": "1", "SLURM_PROCID": "0", "SLURM_LOCALID": "0", "SLURM_NODEID": "0",
           "SLURM_NODELIST": "localhost"}
    run_dir = tmp_path / "run"
    base = [sys.executable, "-m", "difareli.cli.train", "trainer=ddp_slurm", "trainer.accelerator=cpu",
            "trainer.devices=1", "trainer.precision=32-true", f"data.root={synth_store}", "data.resolution=32",
            "data.synth=null", "data.num_workers=0", "data.batch_size=4", "model.preset=tiny", "sample_grid=false",
            "trainer.val_check_interval=2", "trainer.limit_val_batches=1", "logger=[]", "~callbacks.progress_bar",
            "~callbacks.reconstruction_grid", f"hydra.run.dir={run_dir}", f"paths.log_dir={tmp_path}"]
    first = subprocess.run([*base, "trainer.max_steps=6",
                            "+callbacks.preempt._target_=tests.cli.test_scale_slurm.Preempt"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-4000:]
    assert log.read_text().split() == ["requeue", "4242"]  # Lightning asked SLURM to requeue this job id
    hpc = run_dir / "hpc_ckpt_1.ckpt"
    assert torch.load(hpc, map_location="cpu", weights_only=True)["global_step"] == 3

    # The requeued job: the same command (no ckpt_path) picks the hpc checkpoint up and finishes.
    second = subprocess.run([*base, "trainer.max_steps=6"], cwd=tmp_path, env=env, capture_output=True, text=True,
                            timeout=600)
    assert second.returncode == 0, second.stderr[-4000:]
    assert "hpc_ckpt_1.ckpt" in second.stdout + second.stderr  # "Restoring states from the checkpoint path at"
    last = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert last["global_step"] == 6  # continued from step 3, into the same run dir and the same last.ckpt
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["last.ckpt", "step_0000006.ckpt"]
