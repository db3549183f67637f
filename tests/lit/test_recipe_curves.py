"""scripts/recipe_curves.py: recipes compared at equal wall time from their runs' metrics.csv."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _script():
    spec = importlib.util.spec_from_file_location("recipe_curves", ROOT / "scripts" / "recipe_curves.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(root: Path, overrides: list[str], rows: list[tuple[int, float, float]]) -> Path:
    """A run dir whose validations (step, wall seconds, val/dssim/same) are ``rows``, with train rows between."""
    (root / "csv").mkdir(parents=True)
    (root / ".hydra").mkdir()
    (root / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    with open(root / "csv" / "metrics.csv", "w", newline="") as f:
        w = csv.DictWriter(f, ["epoch", "step", "train/loss", "perf/wall_s", "val/dssim/same", "val/loss"])
        w.writeheader()
        for step, wall, dssim in rows:
            w.writerow({"epoch": 0, "step": step - 1, "train/loss": 0.5})
            w.writerow({"epoch": 0, "step": step, "val/dssim/same": dssim, "val/loss": dssim * 2})
            w.writerow({"epoch": 0, "step": step, "perf/wall_s": wall})
    return root


def test_scores_at_the_shortest_runs_wall_time(tmp_path):
    a = _run(tmp_path / "0", ["experiment=reference_cpu", "model.loss.weighting=simple"],
             [(10, 100.0, 0.30), (20, 200.0, 0.25), (30, 300.0, 0.20)])
    b = _run(tmp_path / "1", ["experiment=reference_cpu", "model.loss.weighting=min_snr"],
             [(10, 120.0, 0.28), (20, 250.0, 0.22)])
    _script().main([str(tmp_path / "*"), "--out", str(tmp_path / "out")])
    table = (tmp_path / "out" / "recipe_table.md").read_text()
    assert "within 250 s" in table
    # Run a at 250 s: its last validation at or before it is step 20 (0.25); run b's own last, step 20 (0.22).
    assert "| model.loss.weighting=simple | 0.2500 | 0.5000 | 20 | 200 |" in table
    assert "| model.loss.weighting=min_snr | 0.2200 | 0.4400 | 20 | 250 |" in table
    assert (tmp_path / "out" / "recipe_curves.png").stat().st_size > 1000
    _script().main([str(a), str(b), "--seconds", "150", "--out", str(tmp_path / "o2")])
    assert ("| model.loss.weighting=min_snr | 0.2800 | 0.5600 | 10 | 120 |"
            in (tmp_path / "o2" / "recipe_table.md").read_text())


def test_refuses_folders_without_runs(tmp_path):
    with pytest.raises(SystemExit, match="no run dir with csv/metrics.csv"):
        _script().main([str(tmp_path / "nothing*")])
