"""NaN inputs in the benchmark are failed rows, a killed benchmark resumes, a non-finite loss stops
training without touching the checkpoint, and workers die with their parent."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from difareli.evaluation import tables as T
from tests.helpers import HAS_ESTIMATORS, NO_ESTIMATORS

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def store_copy(synth_store, tmp_path):
    root = tmp_path / "store"
    shutil.copytree(synth_store, root)
    return root


def _bench(root, out, method=None, limit=2):
    from difareli.evaluation.baselines import Identity
    from difareli.evaluation.benchmark import run_benchmark
    from difareli.data.store import EncodingStore

    return run_benchmark(EncodingStore.open(root), method or Identity("identity"), ["same_subject"], out,
                         limit=limit, oracle_light=True, grid_pairs=1, progress=False)


def test_nan_source_encoding_is_a_failed_row(store_copy, tmp_path, capsys):
    first = _bench(store_copy, tmp_path / "clean").records[0]
    src = first.record_id.split("__")[0]
    shape = np.load(store_copy / "records" / src / "shape.npy")
    shape[0] = np.nan
    np.save(store_copy / "records" / src / "shape.npy", shape)
    res = _bench(store_copy, tmp_path / "run")
    assert [r.status for r in res.records] == ["failed", "ok"]
    assert math_nan(res.records[0].dssim) and "FAILED same_subject" in capsys.readouterr().err
    rows = T.read_records(tmp_path / "run" / T.PER_IMAGE_CSV)
    assert rows[0].status == "failed" and rows[1] == res.records[1]
    assert "| 1 (+1 failed) |" in (tmp_path / "run" / "summary.md").read_text()


def math_nan(x):
    return x != x


def test_killed_benchmark_resumes_without_redoing_pairs(store_copy, tmp_path):
    from difareli.evaluation.baselines import Identity
    from difareli.evaluation.benchmark import PARTIAL_CSV

    class Dies(Identity):
        calls = 0

        def relight(self, *a, **k):
            Dies.calls += 1
            if Dies.calls == 3:
                raise KeyboardInterrupt  # killed while relighting the third pair
            return super().relight(*a, **k)

    ref = _bench(store_copy, tmp_path / "ref", limit=4)
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        _bench(store_copy, out, Dies("identity"), limit=4)
    assert len((out / PARTIAL_CSV).read_text().splitlines()) == 3  # header + 2 scored pairs
    Dies.calls = 10  # from now on it relights normally; count the relights of the resumed run
    res = _bench(store_copy, out, Dies("identity"), limit=4)
    assert Dies.calls == 12  # only pairs 3 and 4 were relit
    assert [(r.record_id, r.dssim, r.mse, r.lpips) for r in res.records] == \
        [(r.record_id, r.dssim, r.mse, r.lpips) for r in ref.records]
    assert not (out / PARTIAL_CSV).exists()
    assert ((out / "comparison_same_subject.png").read_bytes()
            == (tmp_path / "ref" / "comparison_same_subject.png").read_bytes())


def test_guard_names_batch_records():
    from difareli.lit.guards import NonFiniteGuard, NonFiniteLossError

    g = NonFiniteGuard()

    class T_:
        global_step, precision = 7, "32-true"

    g.on_train_batch_start(T_(), None, {"record_id": ["s00001_l0", "s00002_l1"]}, 3)
    g.on_before_backward(T_(), None, torch.tensor(0.5))
    with pytest.raises(NonFiniteLossError,
                       match=r"training loss is nan at step 7 \(batch 3, records: s00001_l0, s00002_l1\)"):
        g.on_before_backward(T_(), None, torch.tensor(float("nan")))
    p = torch.nn.Parameter(torch.zeros(3))
    p.grad = torch.tensor([1.0, float("inf"), 0.0])
    with pytest.raises(NonFiniteLossError, match="gradient norm is inf"):
        g.on_before_optimizer_step(T_(), None, torch.optim.SGD([p], lr=1.0))


@pytest.mark.slow
def test_nonfinite_loss_stops_training_and_keeps_last_ckpt(store_copy, tmp_path, monkeypatch):
    import difareli.lit.datamodule
    from difareli.cli.train import train
    from difareli.lit.guards import NonFiniteLossError

    from tests.helpers import compose_train

    base = [f"data.root={store_copy}", "callbacks.reconstruction_grid=null", "data.resolution=32", "data.synth=null",
            "data.num_workers=0", "data.batch_size=4", "model=difareli_pp", "model.preset=tiny", "trainer=cpu",
            "sample_grid=false", "logger=[]", "trainer.limit_val_batches=1", "trainer.val_check_interval=2"]
    train(compose_train(tmp_path, [*base, "trainer.max_steps=2"]))
    last = tmp_path / "checkpoints" / "last.ckpt"
    good = last.read_bytes()
    # One training record with a NaN pixel of its shading reference, past the loader's own check (as a
    # corruption it does not cover would be): the loss turns NaN on its batch and the guard must stop there.
    rid = "s00002_l0"
    shading = np.load(store_copy / "records" / rid / "shading.npy")
    shading[3, 4, 0] = np.nan
    np.save(store_copy / "records" / rid / "shading.npy", shading)
    monkeypatch.setattr(difareli.lit.datamodule, "check_record", lambda arrays, *a: arrays)
    cfg = compose_train(tmp_path, [*base, "trainer.max_steps=40", f"ckpt_path={last}"])
    with pytest.raises(NonFiniteLossError, match=rf"training loss is nan at step \d+ \(batch \d+, records: .*{rid}"):
        train(cfg)
    assert last.read_bytes() == good
    assert all(torch.isfinite(v).all() for v in torch.load(last, weights_only=True)["state_dict"].values()
               if v.is_floating_point())


_POOL = """
import os, sys, time
from concurrent.futures import ProcessPoolExecutor
from difareli.utils.processes import die_with_parent
def nap(_):
    time.sleep(60)
with ProcessPoolExecutor(2, initializer=die_with_parent, initargs=(os.getpid(),)) as pool:
    futs = [pool.submit(nap, i) for i in range(2)]
    time.sleep(0.5)
    print(" ".join(str(p) for p in pool._processes), flush=True)
    time.sleep(60)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_pool_workers_die_with_sigkilled_parent():
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    parent = subprocess.Popen([sys.executable, "-c", _POOL], stdout=subprocess.PIPE, text=True, env=env)
    workers = [int(p) for p in parent.stdout.readline().split()]
    assert len(workers) == 2 and all(_alive(p) for p in workers)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 2.0
    while any(_alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_alive(p) for p in workers)


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(d.name))
            except (OSError, IndexError):
                pass
    return out


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.skipif(not HAS_ESTIMATORS, reason=NO_ESTIMATORS)  # synth's default inputs=estimated
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_killed_synth_leaves_no_worker_and_a_consistent_store(tmp_path, sig):
    from difareli.data.store import EncodingStore

    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": "1"}
    out = tmp_path / "store"
    proc = subprocess.Popen([sys.executable, "-m", "difareli.cli.synth", f"out_dir={out}", "subjects=6", "lights=2",
                             "resolution=32", "workers=2", f"hydra.run.dir={tmp_path / 'run'}",
                             "preview.enabled=false"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    workers: list[int] = []
    deadline = time.monotonic() + 120
    while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
        workers = [c for c in _children(proc.pid) if "python" in Path(f"/proc/{c}/cmdline").read_text(errors="ignore")]
    assert len(workers) >= 2, "the pool never started"
    proc.send_signal(sig)
    if sig == signal.SIGTERM:
        assert proc.wait(60) == 143 and "stopped (SIGTERM)" in proc.stderr.read()
    else:
        proc.wait()
    time.sleep(2.0)
    assert not any(_alive(p) for p in workers)
    store = EncodingStore.open(out, writable=True)  # clears dead writers' scratch folders
    assert store.verify(check_values=True) == []
