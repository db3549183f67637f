"""Checkpoints survive kills and full disks: the atomic writer (difareli.utils.fileio) behind AtomicCheckpointIO."""

from __future__ import annotations

import errno
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from difareli.errors import UserError
from difareli.utils.fileio import torch_save_atomic

SRC = str(Path(__file__).resolve().parents[2] / "src")

# Rewrites last.ckpt forever, alternating two versions, and says when the first write is done.
CHILD = textwrap.dedent("""
    import sys, torch
    from difareli.utils.fileio import torch_save_atomic
    target = sys.argv[1]
    versions = [{"global_step": s, "state_dict": {"w": torch.full((1_500_000,), float(s))}} for s in (1, 2)]
    i = 0
    while True:
        torch_save_atomic(versions[i % 2], target)
        if i == 0:
            print("ready", flush=True)
        i += 1
""")


def _loads(path: Path) -> int:
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    step = int(ckpt["global_step"])
    assert torch.equal(ckpt["state_dict"]["w"], torch.full((1_500_000,), float(step)))  # whole, not torn
    return step


@pytest.mark.slow  # 20 child processes (~1-4 s each: torch import)
def test_kill_at_random_moments_never_leaves_an_unloadable_last_ckpt(tmp_path):
    target = tmp_path / "checkpoints" / "last.ckpt"
    env = {**os.environ, "PYTHONPATH": SRC, "OMP_NUM_THREADS": "1"}
    rng = random.Random(0)
    seen = set()
    for _ in range(20):
        proc = subprocess.Popen([sys.executable, "-c", CHILD, str(target)], env=env, stdout=subprocess.PIPE,
                                text=True)
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(rng.uniform(0.0, 0.25))  # somewhere inside one of the following writes
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        seen.add(_loads(target))
    assert seen <= {1, 2}
    # Leftover temporary files of killed writers sit beside the target, never in its place.
    assert all(p.name.startswith(".last.ckpt.tmp-") for p in target.parent.iterdir() if p != target)


def test_full_disk_names_the_checkpoint_and_keeps_the_previous_one(tmp_path, monkeypatch):
    target = tmp_path / "last.ckpt"
    torch_save_atomic({"global_step": 1, "state_dict": {"w": torch.full((1_500_000,), 1.0)}}, target)

    def full(obj, f, *a, **k):
        f.write(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(UserError, match=r"no space left on the device writing .*last\.ckpt"):
        torch_save_atomic({"global_step": 2}, target)
    monkeypatch.undo()
    assert _loads(target) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]  # the partial temporary file is gone


def test_trainer_config_writes_checkpoints_through_the_atomic_io(tmp_path):
    import hydra

    from difareli.lit.checkpoint_io import AtomicCheckpointIO

    from tests.helpers import compose_train

    for trainer in ("default", "cpu", "ddp_slurm"):
        cfg = compose_train(tmp_path, [f"trainer={trainer}"])
        plugins = [hydra.utils.instantiate(p) for p in cfg.trainer.plugins]
        assert any(isinstance(p, AtomicCheckpointIO) for p in plugins), trainer


def test_a_full_disk_leaves_no_truncated_png(tmp_path, monkeypatch):
    import imageio.v3 as iio
    import numpy as np

    from difareli.utils import viz

    img = np.zeros((8, 8, 3), np.uint8)
    viz.save_png(img, tmp_path / "relit.png")

    def full(path, image, **kw):
        Path(path).write_bytes(b"\x89PNG partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(iio, "imwrite", full)
    with pytest.raises(UserError, match=r"no space left on the device writing .*relit\.png"):
        viz.save_png(img + 1, tmp_path / "relit.png")
    monkeypatch.undo()
    np.testing.assert_array_equal(iio.imread(tmp_path / "relit.png"), img)  # the previous image, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["relit.png"]


def test_a_run_stopped_between_periodic_checkpoints_keeps_its_last_steps(synth_store, tmp_path):
    """Lightning writes ``last`` at train end only when none was written yet: stopping at step 5 with checkpoints
    every 3 steps used to leave last.ckpt at step 3. The stop-aware callback writes it at step 5, with the raw
    weights (not the EMA average) as the resume state."""
    from difareli.cli.train import train

    from tests.helpers import compose_train, tiny_cpu_overrides

    cfg = compose_train(tmp_path, [
        *tiny_cpu_overrides(synth_store, batch_size=2), "model=difareli", "trainer.max_steps=5",
        "trainer.val_check_interval=3", "trainer.limit_val_batches=1", "logger=[]",
        "callbacks.ema.decay=0.9", "callbacks.relight_metrics.enabled=false",
    ])
    train(cfg)
    ckpt = torch.load(tmp_path / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["global_step"] == 5
    raw, ema = ckpt["current_model_state"], ckpt["state_dict"]
    assert any(not torch.equal(raw[k], ema[k]) for k in ema if ema[k].is_floating_point())
