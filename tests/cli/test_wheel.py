"""The package works wherever it is installed: a wheel built from the checkout, installed into a clean folder,
runs a relight with the shipped checkpoint and a 2-step training from a directory that is not the checkout, its
configs found as package data (no project root), and a ./conf folder there extends them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
# A wheel build and two subprocess runs: minutes, and their time depends on the machine's load (the slow tier).
pytestmark = pytest.mark.slow


def _run(args, cwd, env, timeout=600):
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{args[:2]} exit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``(target folder, env)``: the wheel installed with --target; PYTHONPATH puts it before the checkout."""
    root = tmp_path_factory.mktemp("wheel")
    # Build from a copy of the tracked files: a build in the checkout would leave build/ behind.
    src = root / "src_copy"
    files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    for rel in filter(None, files.decode().split("\0")):
        dst = src / rel
        if (REPO / rel).is_file():
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_bytes((REPO / rel).read_bytes())
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH",)}
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(root / "dist"),
          str(src)], root, env)
    wheel = next((root / "dist").glob("difareli-*.whl"))
    target = root / "site"
    _run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(target), str(wheel)], root, env)
    env = {**env, "PYTHONPATH": str(target), "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE",
           "PYTHONWARNINGS": "ignore"}
    return target, env


def test_wheel_holds_the_configs_and_the_shipped_checkpoint(installed):
    target, env = installed
    assert (target / "difareli" / "conf" / "train.yaml").is_file()
    assert (target / "difareli" / "conf" / "model" / "difareli_pp.yaml").is_file()
    assert (target / "difareli" / "checkpoints" / "difareli_pp-synth64.ckpt").is_file()
    assert (target / "hydra_plugins" / "difareli_searchpath" / "difareli_searchpath.py").is_file()
    where = _run([sys.executable, "-c", "import difareli; print(difareli.__file__)"], target.parent, env)
    assert where.strip().startswith(str(target)), where  # the installed copy, not the checkout


def test_installed_wheel_relights_and_trains_outside_the_checkout(installed, tmp_path):
    target, env = installed
    work = tmp_path / "elsewhere"
    work.mkdir()
    py = [sys.executable, "-m"]
    _run([*py, "difareli.cli.synth", f"out_dir={work / 'sf'}", "subjects=4", "lights=2", "resolution=64",
          "workers=1", "inputs=estimated_light"], work, env)  # v2 data: the base install has no estimators
    out = _run([*py, "difareli.cli.relight", "checkpoint=difareli_pp-synth64", f"store={work / 'sf'}",
                "target.yaw=40", "sampler=ddim", "sampler.steps=2", f"out_dir={work / 'relit'}"], work, env)
    assert (work / "relit" / "relit.png").is_file(), out
    # A user's ./conf extends the shipped groups: a model variant of their own, picked by name.
    (work / "conf" / "model").mkdir(parents=True)
    (work / "conf" / "model" / "my_variant.yaml").write_text("defaults:\n  - difareli_pp\n  - _self_\nname: mine\n")
    _run([*py, "difareli.cli.train", "experiment=quickstart", "model=my_variant", f"data.root={work / 'sf'}",
          "trainer.max_steps=2", "trainer.val_check_interval=1", "trainer.limit_val_batches=1", "data.batch_size=2",
          "data.num_workers=0", "sample_grid=false", "data.allow_split_fallback=true", "data.synth=null",
          f"paths.log_dir={work / 'logs'}"],  # data.synth=null: the store as it is (other settings are refused)
         work, env)
    ckpts = list((work / "logs").rglob("last.ckpt"))
    assert ckpts, "no checkpoint written"
    import torch

    ckpt = torch.load(ckpts[0], map_location="cpu", weights_only=True)
    assert ckpt["global_step"] == 2 and ckpt["hyper_parameters"]["name"] == "mine"
