"""The notebooks users open first (``notebooks/*.ipynb``), executed end to end with nbclient.

Each notebook runs in a fresh ``python3`` kernel of this interpreter (a kernelspec written to a temporary
``JUPYTER_PATH``) on a temporary copy, with its parameters given through ``DIFARELI_*`` environment variables:
the relighting notebook on the tiny DiFaReli++ checkpoint and the conftest store (DDIM, 3 steps), the tables
notebook on two run folders written here with known scores. Printed values are recomputed independently.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest


nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"
STEPS = 3


@pytest.fixture(scope="module")
def jupyter_path(tmp_path_factory) -> Path:
    """A folder holding a ``python3`` kernelspec that starts this interpreter (the venv's), whatever is on PATH."""
    root = tmp_path_factory.mktemp("jupyter")
    spec = root / "kernels" / "python3"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (difareli tests)", "language": "python",
    }))
    return root


def execute(name: str, cwd: Path, env: dict[str, str], jupyter_path: Path, monkeypatch):
    """Execute ``notebooks/<name>`` in ``cwd`` with ``env`` set; returns (notebook, stdout text).

    The executed copy is written to ``cwd/<name>`` (the stored notebook keeps no outputs)."""
    for key in [k for k in os.environ if k.startswith("DIFARELI_")]:
        monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    monkeypatch.setenv("JUPYTER_PATH", os.pathsep.join([str(jupyter_path), os.environ.get("JUPYTER_PATH", "")]))
    monkeypatch.setenv("MPLBACKEND", "agg")
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = nbclient.NotebookClient(nb, kernel_name="python3", timeout=300,
                                     resources={"metadata": {"path": str(cwd)}})
    try:
        client.execute()
    finally:
        nbformat.write(nb, cwd / name)
    return nb, stdout(nb)


def stdout(nb) -> str:
    return "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
                   if o.get("output_type") == "stream" and o.get("name") == "stdout")


def test_notebooks_are_stored_without_outputs():
    for path in sorted(NOTEBOOKS.glob("*.ipynb")):
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        for cell in nb.cells:
            if cell.cell_type == "code":
                assert not cell.outputs and cell.execution_count is None, f"{path.name}: clear its outputs"


# ------------------------------------------------------------------------------------ relight_from_checkpoint
@pytest.mark.slow  # a Jupyter kernel runs the notebook: ~20 s loaded (the missing-checkpoint run stays fast)
def test_relight_notebook(tiny_checkpoint, synth_store, jupyter_path, tmp_path, monkeypatch):
    import imageio.v3 as iio
    import torch

    from difareli.lighting import sh
    from difareli.relight.relighter import Relighter
    from difareli.relight.targets import Targets
    from difareli.data.store import EncodingStore

    ckpt = tiny_checkpoint("difareli_pp")
    out = tmp_path / "out"
    env = {"DIFARELI_CHECKPOINT": str(ckpt), "DIFARELI_STORE": str(synth_store), "DIFARELI_SAMPLER": "ddim",
           "DIFARELI_STEPS": str(STEPS), "DIFARELI_OUT": str(out), "DIFARELI_DEVICE": "cpu",
           "DIFARELI_THREADS": "1"}
    _, text = execute("relight_from_checkpoint.ipynb", tmp_path, env, jupyter_path, monkeypatch)

    for png in ("relight_targets.png", "shadow_strength.png", "rotation_yaw_angles.png"):
        img = iio.imread(out / png)
        assert img.ndim == 3 and min(img.shape[:2]) > 100, png
    sheet = iio.imread(out / "rotation_yaw.png")  # rotation_video's contact sheet: 10 frames a row, 2 px gaps
    assert sheet.shape[:2] == (2 * (32 + 2) + 2, 10 * (32 + 2) + 2)
    frames = iio.imread(out / "rotation_yaw.gif", index=None)  # the notebook asks for a GIF to show inline
    assert frames.shape[:3] == (12, 32, 32)
    assert "difareli_pp" in text and "parameters" in text

    line = next(l for l in text.splitlines() if l.startswith("RESULT "))
    result = json.loads(line[len("RESULT "):])
    store = EncodingStore.open(synth_store)
    rid = store.ids(split="test")[0]
    other_id = next(r for r in store.ids(subject=store.meta(rid)["subject"]) if r != rid)
    assert (result["record"], result["target_record"]) == (rid, other_id)

    # The same relighting through the API, independently of the notebook's code.
    ambient = np.zeros((9, 3))
    ambient[0] = 0.3 / sh.SH_CONSTANTS[0]
    own = np.asarray(store.read(rid, ["light"])["light"], dtype=np.float64)
    other = store.read(other_id, ["light", "shadow"])
    targets = [([np.asarray(other["light"])], [float(other["shadow"][0])]),
               ([sh.directional_light((-0.7, 0.45, 0.55), 1.0) + ambient], None),
               ([sh.yaw(own, 60.0)], None)]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        relighter = Relighter(ckpt, {"name": "ddim", "steps": STEPS}, device="cpu")
        expected = [float(relighter.relight(relighter.source(store, rid),
                                            Targets.of(lights, shadows))[0].mean() / 255.0)
                    for lights, shadows in targets]
    finally:
        torch.set_num_threads(threads)
    np.testing.assert_allclose(result["means"], expected, rtol=0, atol=1e-6)


def test_relight_notebook_with_a_missing_checkpoint_says_how_to_get_one(jupyter_path, tmp_path, monkeypatch):
    env = {"DIFARELI_CHECKPOINT": str(tmp_path / "nope.ckpt"), "DIFARELI_OUT": str(tmp_path / "out")}
    with pytest.raises(nbclient.exceptions.CellExecutionError) as err:
        execute("relight_from_checkpoint.ipynb", tmp_path, env, jupyter_path, monkeypatch)
    assert "No checkpoint found" in str(err.value)
    assert "difareli-train experiment=quickstart" in str(err.value)


@pytest.mark.skipif("difareli_pp-synth64" not in __import__("difareli.checkpoints.zoo").checkpoints.zoo.available(),
                    reason="no shipped difareli_pp-synth64")
@pytest.mark.slow  # a Jupyter kernel relights with the shipped reference: ~35 s on the loaded 2-core CI
def test_relight_notebook_runs_on_the_shipped_reference_by_default(jupyter_path, tmp_path, monkeypatch):
    """No parameters but the step count: the shipped checkpoint on SynthFaces generated in the notebook."""
    import imageio.v3 as iio

    out = tmp_path / "out"
    env = {"DIFARELI_STEPS": str(STEPS), "DIFARELI_OUT": str(out), "DIFARELI_DEVICE": "cpu", "DIFARELI_THREADS": "1",
           "DIFARELI_FRAMES": "6"}
    _, text = execute("relight_from_checkpoint.ipynb", tmp_path, env, jupyter_path, monkeypatch)
    assert "difareli_pp-synth64.ckpt" in text and f"generated {out / 'synthfaces'}" in text
    frames = iio.imread(out / "rotation_yaw.gif", index=None)  # the notebook asks for a GIF to show inline
    assert frames.shape[:3] == (6, 64, 64)
    result = json.loads(next(l for l in text.splitlines() if l.startswith("RESULT "))[len("RESULT "):])
    # the three targets (another record's light, a directional light, a 60-degree yaw) give three different images
    assert len({round(m, 4) for m in result["means"]}) == 3


# ------------------------------------------------------------------------------------------ benchmark_tables
def _write_runs(root: Path) -> dict[tuple[str, str], dict[str, list[float]]]:
    """Two run folders (one method each) in tables.py's per-image schema; returns the values written."""
    from difareli.evaluation import tables

    rng = np.random.default_rng(7)
    values: dict[tuple[str, str], dict[str, list[float]]] = {}
    for run, (method, scale) in enumerate([("lambertian", 1.0), ("difareli_pp/ddim-3", 0.5)]):
        records = []
        for protocol, n in (("same", 4), ("different", 3)):
            v = {k: list(scale * rng.uniform(0.01, 0.3, n)) for k in ("dssim", "mse", "lpips")}
            v["seconds"] = list(rng.uniform(0.05, 2.0, n))
            values[(method, protocol)] = v
            records += [tables.Record(method, protocol, f"{protocol}_{i}", v["dssim"][i], v["mse"][i], v["lpips"][i],
                                      v["seconds"][i]) for i in range(n)]
        tables.write_records(root / f"job{run}" / tables.PER_IMAGE_CSV, records)
    return values


@pytest.mark.slow  # a Jupyter kernel runs the whole notebook: ~10 s (the no-runs run stays fast)
def test_tables_notebook(jupyter_path, tmp_path, monkeypatch):
    runs = tmp_path / "multirun"
    values = _write_runs(runs)
    out = tmp_path / "out"
    nb, text = execute("benchmark_tables.ipynb", tmp_path, {"DIFARELI_RUNS": str(runs / "*"),
                                                            "DIFARELI_OUT": str(out)}, jupyter_path, monkeypatch)
    for (method, protocol), v in values.items():
        row = next(l for l in text.splitlines() if l.startswith(f"| {method} |"))
        for metric in ("dssim", "mse", "lpips"):
            x = np.asarray(v[metric])
            mean, se = float(x.mean()), float(x.std(ddof=1) / math.sqrt(x.size))
            assert f"{mean:.4f} ± {se:.4f}" in row, (method, protocol, metric, row)
            assert repr(mean) in text  # the full-precision CSV
        secs = values[(method, "same")]["seconds"] + values[(method, "different")]["seconds"]
        assert row.endswith(f"| {float(np.mean(secs)):.3g} |")
    assert "(i) same subject DSSIM" in text and "(ii) different subject LPIPS" in text
    for name in ("table.md", "table.csv", "table.tex", "metrics.png"):
        assert (out / name).is_file(), name


@pytest.mark.slow  # a notebook kernel: the default run has to finish in minutes at load 4
def test_tables_notebook_without_runs_explains(jupyter_path, tmp_path, monkeypatch):
    nb, text = execute("benchmark_tables.ipynb", tmp_path, {"DIFARELI_OUT": str(tmp_path / "out")}, jupyter_path,
                       monkeypatch)
    shown = "".join(o.get("data", {}).get("text/markdown", "") for c in nb.cells if c.cell_type == "code"
                    for o in c.get("outputs", []))
    assert "No benchmark runs found" in shown and "difareli-benchmark" in shown
    assert "±" not in text and not (tmp_path / "out" / "table.md").exists()
