"""scripts/reference_suite.py: identity, Lambertian and each model on a store, one table per store, the model at
the default sampler, and its rows equal to the benchmark's own run of the same method and pairs."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from difareli.evaluation import tables
from difareli.evaluation.baselines import Identity
from difareli.evaluation.benchmark import finished_run
from difareli.data.store import EncodingStore
from difareli.synth.command import synth_command
from difareli.diffusion import DEFAULT_SAMPLER, PRESETS

from tests.helpers import CONF

ROOT = CONF.parent  # conf/ sits at the top of the repository
pytestmark = pytest.mark.usefixtures("one_thread")


def test_suite_tables_every_model_beside_the_baselines_at_the_default_sampler(tiny_checkpoint, synth_store,
                                                                             tmp_path):
    ckpt = tiny_checkpoint("difareli_pp")
    out = tmp_path / "suite"
    cmd = [sys.executable, str(ROOT / "scripts" / "reference_suite.py"), "--store", str(synth_store), "--pairs", "2",
           "--out", str(out), "--models", str(ckpt)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = (out / "suite.md").read_text()
    default = PRESETS[DEFAULT_SAMPLER]
    row = f"difareli_pp/{default.name}-{default.steps}"
    for piece in (f"**{synth_store}**: 2 pairs per protocol", "| identity |", "| lambertian |", f"| {row} |",
                  synth_command(synth_store), f"--store {synth_store} --pairs 2"):
        assert piece in text, piece
    # The table is the runs' own per-image scores, summarised (nothing re-scored or rounded away).
    records = [r for d in ("identity", "lambertian", row.replace("/", "_"))
               for r in tables.read_records(out / synth_store.name / d / tables.PER_IMAGE_CSV)]
    assert {r.method for r in records} == {"identity", "lambertian", row}
    assert tables.summarize(records).to_markdown() in text
    # A rerun resumes every run (the same rows, no new relights).
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, check=False)
    assert again.returncode == 0 and (out / "suite.md").read_text() == text
    # What is reused: a finished run with exactly the settings asked for; another limit is another run.
    store, where = EncodingStore.open(synth_store), out / synth_store.name / "identity"
    protocols = ["same_subject", "different_subject"]
    kept = finished_run(store, Identity(), protocols, where, limit=2)
    assert kept is not None and {r.record_id for r in kept.records} == {r.record_id for r in records
                                                                          if r.method == "identity"}
    assert finished_run(store, Identity(), protocols, where, limit=3) is None
    assert finished_run(store, Identity(), protocols, where, limit=2, rule="composite") is None
