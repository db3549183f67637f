"""scripts/gpu_check.sh at toy size on CPU: the report's keys, positive finite figures, and FLOP bookkeeping.

The script blocks hydra/omegaconf/kornia/trimesh/wandb imports itself, so passing here also proves its import
chain runs on a GPU image without them."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
# The script in a fresh interpreter builds, times and trains toy models: minutes idle, past 600 s on the loaded 2-core
# CI. The fast tier keeps its pieces: tests/perf/test_bench_modes.py (every mode) and test_perf.py (FLOP counts).
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("gpu_check")
    env = {**os.environ, "PYTHON": sys.executable, "OMP_NUM_THREADS": "1", "OUT": str(out),
           "CUDA_VISIBLE_DEVICES": ""}
    proc = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh"), "--small"], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (out / "gpu_check.md").read_text().startswith("# GPU check")
    return json.loads((out / "gpu_check.json").read_text())


def test_report_has_every_section(report):
    assert set(report) == {"env", "flops", "unet", "relight", "train", "skipped"}
    assert report["env"]["small"] is True and report["env"]["device"] == "cpu"
    assert {(u["mode"], u["batch"]) for u in report["unet"]} == {(m, b) for m in ("fp32", "bf16", "bf16+cuda_graphs")
                                                                 for b in (1, 2)}
    assert set(report["relight"]) == {"preset", "resolution", "unipc", "ddim", "rotation"}
    assert report["relight"]["rotation"]["targets"] == 3 and report["relight"]["ddim"]["passes"] == 3 * 4


def test_figures_positive_and_finite(report):
    rows = report["unet"] + report["relight"]["unipc"] + [report["relight"]["ddim"], report["relight"]["rotation"]]
    for r in rows:
        for k in ("ms_per_pass", "TFLOPs", "mfu", "seconds", "invert_s", "decode_s"):
            if k in r:
                assert math.isfinite(r[k]) and r[k] > 0, (k, r)
    for k in ("images_per_s", "step_GFLOP", "achieved_GFLOPs"):
        assert math.isfinite(report["train"][k]) and report["train"][k] > 0


def test_flop_bookkeeping(report):
    f = report["flops"][0]
    for u in report["unet"]:  # TFLOP/s = GFLOP per pass x batch / ms
        assert u["TFLOPs"] == pytest.approx(f["unet_pass_GFLOP"] * u["batch"] / u["ms_per_pass"], rel=1e-9)
    # A training step is forward + backward (~2x forward) of UNet and Modulator over the batch.
    t = report["train"]
    ratio = t["step_GFLOP"] / (t["batch"] * (f["unet_pass_GFLOP"] + f["modulator_GFLOP"]))
    assert 2.5 < ratio < 3.5
