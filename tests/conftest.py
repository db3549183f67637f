"""Shared test fixtures."""

import os

# Before torch loads OpenMP: idle threads sleep instead of spinning, so a test beside another busy process (a
# benchmark, a training, the other tests' subprocesses) is not slowed many times over by threads waiting hot.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# One thread per test process (and the CLI subprocesses tests start): the suite's tensors are small, and on a
# 2-core machine that is busy with anything else a second thread made tiny trainings 4-20x slower (measured:
# a 10-step resume test took 244 s beside a benchmark and a training).
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def synth_store(tmp_path_factory):
    """A small SynthFaces store (8 subjects x 2 lights, 32 px), generated once per test session."""
    from difareli.synth.generator import generate

    root = tmp_path_factory.mktemp("synthfaces") / "store"
    generate(out_dir=str(root), subjects=8, lights=2, resolution=32, seed=0)
    return root


@pytest.fixture(scope="session")
def tiny_checkpoint(synth_store, tmp_path_factory):
    """Factory: path to a briefly trained tiny checkpoint of a model config ("difareli_pp" or "difareli")
    on ``synth_store``; each model is trained once per session (~20 steps)."""
    from pathlib import Path

    from difareli.cli.train import train

    from .helpers import compose_train

    cache: dict[str, Path] = {}

    def get(model: str = "difareli_pp") -> Path:
        if model not in cache:
            out = tmp_path_factory.mktemp(f"ckpt_{model}")
            cfg = compose_train(out, [
                f"data.root={synth_store}", "data.resolution=32", "data.synth=null", "data.num_workers=0",
                "data.batch_size=4", f"model={model}", "model.preset=tiny", "trainer=cpu", "trainer.max_steps=20",
                "trainer.val_check_interval=20", "trainer.limit_val_batches=1", "sample_grid=false", "logger=[]",
                "callbacks.ema.decay=0.9",
            ])
            train(cfg)
            cache[model] = out / "checkpoints" / "last.ckpt"
        return cache[model]

    return get


@pytest.fixture(scope="module")
def one_thread():
    """One intra-op thread for modules of small-tensor tests: on a shared 2-core CPU a second OpenMP thread
    spin-waits and made tiny convolutions 16-100x slower; restored afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
