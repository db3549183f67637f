"""DDP on 2 CPU processes (gloo) through the real CLI: data sharded over ranks, per-rank noise, one checkpoint
equal to what rank 0 (and rank 1) hold, EMA included; then resume that checkpoint on a single device."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import pytest
import torch

from tests.helpers import compose_train

REPO = Path(__file__).resolve().parents[2]


class RankProbe(L.Callback):
    """Test probe, instantiated from the command line in every rank: writes what this rank saw."""

    def __init__(self, out_dir: str):
        self.out = Path(out_dir)
        self.ids: list[str] = []

    def on_train_start(self, trainer, pl_module) -> None:
        self.seed = torch.initial_seed()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self.ids.append([trainer.current_epoch, list(batch["record_id"])])

    def on_save_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        # Runs after the EMA callback put the average into state_dict: what each rank would have saved.
        r = trainer.global_rank
        torch.save({k: v.detach().clone() for k, v in checkpoint["state_dict"].items()},
                   self.out / f"state_rank{r}_step{trainer.global_step}.pt")

    def on_fit_end(self, trainer, pl_module) -> None:
        doc = {"ids": self.ids, "seed": self.seed, "world_size": trainer.world_size,
               "val_loss": float(trainer.callback_metrics["val/loss"])}
        (self.out / f"rank{trainer.global_rank}.json").write_text(json.dumps(doc))


def _overrides(store: Path) -> list[str]:
    return [f"data.root={store}", "data.resolution=32", "data.synth=null", "data.num_workers=0",
            "data.batch_size=4", "model.preset=tiny", "sample_grid=false", "trainer.limit_val_batches=1",
            "trainer.val_check_interval=2", "callbacks.ema.decay=0.5", "logger=csv"]


@pytest.mark.slow  # three interpreters (launcher + 2 ranks' start-up): ~40 s idle, ~2 min on the loaded 2-core CI
def test_ddp_two_cpu_processes_then_resume_on_one(synth_store, tmp_path):
    probe = tmp_path / "probe"
    probe.mkdir()
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "difareli.cli.train", "trainer=ddp_cpu", "trainer.max_steps=2",
           *_overrides(synth_store), "~callbacks.progress_bar", "~callbacks.reconstruction_grid",
           "+callbacks.probe._target_=tests.cli.test_scale_ddp.RankProbe", f"+callbacks.probe.out_dir={probe}",
           f"hydra.run.dir={run_dir}", f"paths.log_dir={tmp_path}"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "src"), str(REPO)]), "OMP_NUM_THREADS": "1",
           "PYTHONWARNINGS": "ignore"}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    print(f"DDP 2 x CPU (gloo), 2 steps + 1 val batch: {time.perf_counter() - t0:.1f} s wall")
    assert proc.returncode == 0, proc.stderr[-4000:]

    ranks = [json.loads((probe / f"rank{r}.json").read_text()) for r in (0, 1)]
    assert [r["world_size"] for r in ranks] == [2, 2]
    # DistributedSampler: each rank 2 batches of 4; within an epoch the ranks' records are disjoint.
    assert [len(r["ids"]) for r in ranks] == [2, 2] and all(len(b) == 4 for r in ranks for _, b in r["ids"])
    for epoch in {e for r in ranks for e, _ in r["ids"]}:
        seen = [{i for e, b in r["ids"] if e == epoch for i in b} for r in ranks]
        assert seen[0] and seen[1] and not seen[0] & seen[1], (epoch, seen)
    assert ranks[1]["seed"] == ranks[0]["seed"] + 1  # per-rank training noise (DiffusionModule.setup)
    assert ranks[0]["val_loss"] == ranks[1]["val_loss"]  # val/loss synced over ranks

    # Checkpoints written once, by rank 0, into the one run dir; rank 1 wrote no files of its own.
    ckpts = sorted(p.name for p in (run_dir / "checkpoints").iterdir())
    assert ckpts == ["last.ckpt", "step_0000002.ckpt"]
    assert not list(run_dir.rglob("*rank*")) and not list(REPO.glob("outputs"))
    saved = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert saved["global_step"] == 2 and "averaging_state" in saved  # the EMA state travels with it
    held = [torch.load(probe / f"state_rank{r}_step2.pt", weights_only=True) for r in (0, 1)]
    assert held[0].keys() == saved["state_dict"].keys()
    for k, v in saved["state_dict"].items():
        if k in ("ns_mean", "ns_std"):  # rewritten exactly by DiffusionModule.on_save_checkpoint afterwards
            torch.testing.assert_close(v, held[0][k], rtol=0, atol=1e-5)
            continue
        assert torch.equal(v, held[0][k]), k  # the file is what rank 0 held ...
        assert torch.equal(v, held[1][k]), k  # ... and DDP kept rank 1 identical

    # Resume the 2-process checkpoint on one process: continues from step 2.
    from difareli.cli.train import train

    cfg = compose_train(tmp_path / "resume", [*_overrides(synth_store), "trainer=cpu", "trainer.max_steps=4",
                                              "logger=[]", f"ckpt_path={run_dir / 'checkpoints' / 'last.ckpt'}"])
    out = train(cfg)
    assert out["trainer"].global_step == 4 and out["trainer"].world_size == 1
    assert torch.isfinite(out["trainer"].callback_metrics["val/loss"])
