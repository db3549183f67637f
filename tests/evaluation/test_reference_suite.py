"""scripts/reference_suite.py: identity, Lambertian and each model on a store, one table per store, the model at
the default sampler, and its rows equal to the benchmark's own run of the same method and pairs."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from difareli.evaluation import tables
from difareli.evaluation.baselines import Identity
from difareli.evaluation.benchmark import BenchmarkJob
from difareli.evaluation.scoring import Scoring
from difareli.data.store import EncodingStore
from difareli.synth.command import synth_command
from difareli.diffusion import DEFAULT_SAMPLER, PRESETS

from tests.helpers import CONF

ROOT = CONF.parent  # conf/ sits at the top of the repository
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.slow  # the script end to end in a subprocess; the formatting is tested below on built records
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
                  synth_command(synth_store), f"--store {synth_store} --pairs 2",
                  "Paired differences, every two rows on the same pairs:", f"| (i) same subject | DSSIM | lambertian | "
                  f"{row} | 2 |", "At the 5% level (Wilcoxon p < 0.05",
                  "By the target light's category (light_category):",
                  "| Protocol | Stratum | Method | DSSIM | MSE | LPIPS | n |"):
        assert piece in text, piece
    assert (out / synth_store.name / "paired.csv").read_text().startswith("protocol,metric,a,b,n,mean_b_minus_a")
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
    kept = BenchmarkJob.of(store, Identity(), protocols, where, limit=2).finished()
    assert kept is not None and {r.record_id for r in kept.records} == {r.record_id for r in records
                                                                          if r.method == "identity"}
    assert BenchmarkJob.of(store, Identity(), protocols, where, limit=3).finished() is None
    assert BenchmarkJob.of(store, Identity(), protocols, where, limit=2,
                           scoring=Scoring.of(store, "composite")).finished() is None


def _suite_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("reference_suite", ROOT / "scripts" / "reference_suite.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_suite_comparisons_and_strata_on_built_records(tmp_path):
    """A model better than Lambertian by 0.02 DSSIM on every pair is significant, its CI at exactly -0.02; a second
    model equal to the first plus symmetric noise is not; the strata tables are the records' own means."""
    import numpy as np

    rng = np.random.default_rng(5)
    n = 20
    base = rng.uniform(0.15, 0.35, n)
    eps = np.repeat(rng.uniform(0.001, 0.01, n // 2), 2) * np.tile([1, -1], n // 2)
    info = lambda i: {"light_category": ["hard", "soft"][i % 2], "shadow_share": ["0.01", "0.2"][i // 10]}  # noqa

    def rows(method, dssim):
        return [tables.Record(method, p, f"r{i:02d}", float(v), 0.01, 0.1, 0.5, info=info(i))
                for p in ("same", "different") for i, v in enumerate(dssim)]

    records = (rows("identity", base + 0.1) + rows("lambertian", base) + rows("model", base - 0.02)
               + rows("model2", base - 0.02 + eps))
    methods = ["identity", "lambertian", "model", "model2"]
    text = _suite_module().comparisons(records, methods, tmp_path / "paired.csv", n_boot=1000)
    assert "| (i) same subject | DSSIM | lambertian | model | 20 | -0.02 | [-0.02, -0.02] |" in text
    assert "| (ii) different subject | DSSIM | identity | model | 20 | -0.12 | [-0.12, -0.12] |" in text
    sentence = next(line for line in text.splitlines() if line.startswith("At the 5% level"))
    yes, no = sentence.split("; not significant: ")
    groups = dict(g.split(": ", 1) for g in yes.split("significant: ", 1)[1].split("; "))
    dssim = groups["(i) same subject DSSIM"]
    for pair in ("model better than lambertian", "model better than identity", "lambertian better than identity",
                 "model2 better than lambertian", "model2 better than identity"):
        assert pair in dssim, pair
    assert "(i) same subject DSSIM: model vs model2" in no and "(ii) different subject DSSIM: model vs model2" in no
    assert "model vs model2" not in yes and "(i) same subject MSE: identity vs lambertian (p=n/a)" in no
    assert len((tmp_path / "paired.csv").read_text().splitlines()) == 1 + 6 * 2 * 3  # 6 method pairs, 2 protocols
    # the strata: the first 10 pairs in shadow [0, 0.05), the last 10 in [0.15, 0.3); categories alternate
    assert "By the target light's category (light_category):" in text
    hard = next(line for line in text.splitlines() if line.startswith("| (i) same subject | light_category=hard | "
                                                                       "lambertian |"))
    assert f"{base[0::2].mean():.4f} ± {base[0::2].std(ddof=1) / np.sqrt(10):.4f}" in hard and hard.endswith("| 10 |")
    low = next(line for line in text.splitlines() if line.startswith("| (ii) different subject | shadow [0, 0.05) | "
                                                                      "model |"))
    assert f"**{(base[:10] - 0.02).mean():.4f} ± " in low  # the best DSSIM of its stratum, in bold
    assert "shadow [0.15, 0.3) | identity |" in text and "bins [0.0, 0.05, 0.15, 0.3, 1.0]" in text


def test_card_claims_replace_their_own_section_in_both_copies_of_a_card(tmp_path, monkeypatch):
    """--cards writes the paired-comparison sentence into <name>.md and <name>/README.md, before "Intended use",
    and a rerun replaces that section (the rest of the card kept byte for byte)."""
    import importlib.util

    from difareli.checkpoints import zoo

    spec = importlib.util.spec_from_file_location("reference_suite", ROOT / "scripts" / "reference_suite.py")
    suite = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(suite)
    monkeypatch.setattr(zoo, "SHIPPED_DIR", tmp_path)
    card = "# m\n\n## Benchmark\n\ntable\n\n## Intended use\n\nresearch\n"
    (tmp_path / "m").mkdir()
    for path in (tmp_path / "m.md", tmp_path / "m" / "README.md"):
        path.write_text(card)
    suite.write_card_claims("m", ["first claim"], ["cmd 1"])
    suite.write_card_claims("m", ["second claim"], ["cmd 2"])
    for path in (tmp_path / "m.md", tmp_path / "m" / "README.md"):
        text = path.read_text()
        assert text.count(suite.CLAIMS_HEADING) == 1 and "second claim" in text and "first claim" not in text
        assert text.index("second claim") < text.index("## Intended use")
        assert text.startswith("# m\n\n## Benchmark\n\ntable\n") and text.endswith("## Intended use\n\nresearch\n")
