"""difareli.jobs.compare: the model against identity and the Lambertian ratio image, and its model-card facts."""

from __future__ import annotations

from pathlib import Path

import pytest

from difareli.evaluation.baselines import Identity, LambertianRatio
from difareli.evaluation.benchmark import run_benchmark
from difareli.jobs.compare import PROTOCOLS, compare_to_baselines, slug
from difareli.lighting.light_fit import LightFit
from difareli.runtime.core import Runtime
from difareli.data.store import EncodingStore

pytestmark = pytest.mark.usefixtures("one_thread")
SAMPLER = {"name": "ddim", "steps": 2}


@pytest.fixture(scope="module")
def comparison(synth_store, tiny_checkpoint, tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    return out, compare_to_baselines(synth_store, tiny_checkpoint("difareli_pp"), SAMPLER, out, pairs=2,
                                     runtime={"device": "cpu"})


def scores(records):
    return {(r.protocol, r.record_id): (r.status, r.dssim, r.mse, r.lpips) for r in records}


@pytest.mark.parametrize("method", ["identity", "lambertian"])
def test_baseline_rows_equal_direct_benchmark_runs(comparison, synth_store, tmp_path, method):
    _, c = comparison
    fit = LightFit()
    m = Identity() if method == "identity" else LambertianRatio(estimator=fit)
    direct = run_benchmark(EncodingStore.open(synth_store), m, list(PROTOCOLS), tmp_path, limit=2, estimator=fit,
                           grid_pairs=0, save_images=False, progress=False)
    assert scores(c.runs[method].records) == scores(direct.records) and len(direct.records) == 4
    for p in ("same", "different"):
        for metric in ("dssim", "mse", "lpips"):
            assert c.table.cells[(method, p)][metric] == direct.table.cells[(method, p)][metric]


def test_one_table_of_three_rows_and_their_runs(comparison):
    out, c = comparison
    model = "difareli_pp/ddim-2"
    assert c.table.methods == ["identity", "lambertian", model] and set(c.table.protocols) == {"same", "different"}
    assert all(c.table.cells[(model, p)]["dssim"].n == 2 for p in c.table.protocols)
    assert [r.method for r in c.records] == ["identity"] * 4 + ["lambertian"] * 4 + [model] * 4
    for name, run in c.runs.items():  # each method's run written into its own folder
        assert run.paths and all(Path(p).is_relative_to(out / slug(name)) for p in run.paths.values())
    assert slug(model) == "difareli_pp_ddim-2"
    assert c.seconds["total"] >= sum(c.seconds[m] for m in c.runs) > 0


def test_card_facts_state_pairs_sampler_runtime_and_inputs(comparison):
    _, c = comparison
    f = c.facts
    assert f["pairs"] == {"same": 2, "different": 2} and f["protocols"] == list(PROTOCOLS)
    runtime = f"{Runtime(device='cpu').precision} on cpu"  # the default: bf16 on a CPU with native bf16, else fp32
    assert f["sampler"] == "ddim-2" and f["runtime"] == runtime and f["model"] == "difareli_pp/ddim-2"
    assert f["inputs"].startswith("target lights fitted to the light-source images (not the oracle), target c: ")
    assert f["inputs"].endswith(c.runs["difareli_pp/ddim-2"].provenance["target c"])
    assert f["table"] == c.table.to_markdown() and f["seconds"] == c.seconds["total"]
    text = c.card_benchmark("of the test split")
    assert text.startswith("2 test pairs per protocol of the test split, target lights fitted")
    assert f", ddim-2, {runtime} (" in text and text.endswith("s):\n\n" + f["table"])
