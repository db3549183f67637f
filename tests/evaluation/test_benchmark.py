"""Benchmark loop, its CLI and difareli-table on the tiny SynthFaces store."""

import json

import numpy as np
import pytest

from difareli.evaluation import tables
from difareli.evaluation.baselines import Identity, Oracle
from difareli.evaluation.benchmark import run_benchmark
from difareli.evaluation.scoring import Scoring
from difareli.evaluation.pairs import StoredFace, load_pairs
from difareli.data.store import EncodingStore

from tests.helpers import compose_train

BOTH = ["same_subject", "different_subject"]


# Small tensors: one intra-op thread (conftest.one_thread) avoids OpenMP spin-waits on a shared CPU.
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def store(synth_store):
    return EncodingStore.open(synth_store)


def test_a_method_that_reads_a_shadow_map_is_given_the_light_sources_key_sun(store, tmp_path):
    """A method whose model reads a target shadow map is handed each pair's key sun, found from the light-source
    record's cast shadows under its fitted light (``render.sun_fit``); ``target_sun=peak`` hands None; the choice
    is a recorded setting (a resumed run with the other is refused) and a wrong value is one line."""
    from types import SimpleNamespace

    from difareli.errors import UserError
    from difareli.lighting.light_fit import LightFit
    from difareli.render import sun_fit

    seen = []

    class Marching(Identity):
        relighter = SimpleNamespace(model_inputs=("shading", "shadow_map"), spec=None, model=None,
                                    runtime=SimpleNamespace(precision="32-true"))

        def relight(self, source, target_light, target_shadow=None, target=None, target_sun=None):
            seen.append(target_sun)
            return super().relight(source, target_light, target_shadow, target)

    kw = dict(limit=2, progress=False, grid_pairs=0, save_images=False)
    res = run_benchmark(store, Marching("marching"), ["different_subject"], tmp_path / "a", **kw)
    pairs = load_pairs(store, ["different_subject"], limit=2)["different_subject"]
    for pair, got in zip(pairs, seen, strict=True):
        arrays = store.read(pair.light_source, [k for k in sun_fit.ENCODINGS if store.available(k)])
        want = sun_fit.fit_sun(arrays, LightFit().from_store(store, pair.light_source)).direction
        np.testing.assert_array_equal(got, want)
    assert "cast shadows" in res.provenance["target sun"]
    seen.clear()
    peak = Scoring.of(store, target_sun="peak")
    run_benchmark(store, Marching("marching"), ["different_subject"], tmp_path / "b", scoring=peak, **kw)
    assert seen == [None, None]
    with pytest.raises(UserError, match="target_sun"):  # the rows in "a" were marched toward the found suns
        run_benchmark(store, Marching("marching"), ["different_subject"], tmp_path / "a", scoring=peak, **kw)
    with pytest.raises(UserError, match="target_sun='sky': use one of shadows, peak"):
        Scoring.of(store, target_sun="sky")


def test_load_pairs_limit_spreads_over_the_list(store):
    full = load_pairs(store, BOTH)
    doc = json.loads((store.root / "protocols.json").read_text())
    assert [p.source for p in full["same_subject"]] == [r["source"] for r in doc["same_subject"]]
    n = len(full["different_subject"])
    assert n >= 3
    two = load_pairs(store, ["different_subject"], limit=2)["different_subject"]
    assert two == [full["different_subject"][0], full["different_subject"][n - 1]]
    with pytest.raises(ValueError, match="unknown protocol"):
        load_pairs(store, ["nope"])


def test_a_method_is_given_the_input_and_the_ground_truth_as_stored_faces(store, tmp_path):
    """run_benchmark hands a Method each pair's input record as a StoredFace (its store, id, encodings) and the
    ground-truth record as ``target``; a StoredFace reads each encoding from the store once."""
    seen = []

    class Recording(Identity):
        def relight(self, source, target_light, target_shadow=None, target=None, target_sun=None):
            assert target_sun is None  # no shadow map read: no key sun fitted for it
            seen.append((source, target))
            return super().relight(source, target_light, target_shadow, target)

    res = run_benchmark(store, Recording("recording"), ["same_subject"], tmp_path, limit=2, progress=False,
                        grid_pairs=0, save_images=False)
    pairs = load_pairs(store, ["same_subject"], limit=2)["same_subject"]
    assert [(s.id, t.id) for s, t in seen] == [(p.source, p.target) for p in pairs]
    assert all(isinstance(f, StoredFace) and f.store is store for pair in seen for f in pair)
    np.testing.assert_array_equal(seen[0][0].image, store.read(pairs[0].source, ["image"])["image"])
    assert [r.status for r in res.records] == ["ok", "ok"]
    face = StoredFace(store, pairs[0].source)
    assert face.read(["image"])["image"] is face.image and set(face.read()) == set(store.encodings)


def test_oracle_scores_exactly_zero(store, tmp_path):
    res = run_benchmark(store, Oracle(), BOTH, tmp_path, progress=False, grid_pairs=1)
    pairs = load_pairs(store, BOTH)
    assert len(res.records) == sum(len(v) for v in pairs.values())
    for r in res.records:
        assert (r.dssim, r.mse, r.lpips) == (0.0, 0.0, 0.0)
    cells = res.table.cells
    assert cells[("oracle", "same")]["mse"].mean == 0.0 and cells[("oracle", "different")]["lpips"].mean == 0.0


def test_identity_mse_is_the_direct_masked_mse(store, tmp_path):
    res = run_benchmark(store, Identity(), BOTH, tmp_path, progress=False, oracle_light=True)
    pairs = {(p.protocol, p.id): p for v in load_pairs(store, BOTH).values() for p in v}
    proto = {"same": "same_subject", "different": "different_subject"}
    for r in res.records:
        p = pairs[(proto[r.protocol], r.record_id)]
        src = store.read(p.source, ["image"])["image"] / 255.0
        gt = store.read(p.target, ["image", "face_mask"])
        m = np.asarray(gt["face_mask"])
        direct = ((src - gt["image"] / 255.0)[m] ** 2).mean()
        assert r.mse == pytest.approx(direct, rel=1e-12) and r.mse > 1e-4
    assert not res.light_errors  # oracle lights: nothing estimated


def _bench_cfg(out, store_root, *overrides):
    # num_threads=null: leave the test session's torch thread count alone.
    return compose_train(out, [f"store={store_root}", "progress=false", "num_threads=null", *overrides],
                         config_name="benchmark")


def test_lambertian_source_light_is_fitted_once_per_record_and_scored_as_relit(store, tmp_path):
    """The Lambertian baseline fits each source record's light once however many pairs it is in, and the
    benchmark's source-light error is that very fit's (not a second fit): counted through the estimator."""
    from difareli.evaluation.baselines import LambertianRatio
    from difareli.evaluation.pairs import Lights
    from difareli.lighting.light_fit import LightFit

    class Counting(LightFit):
        def __init__(self):
            super().__init__()
            self.calls = []

        def from_store(self, st, record_id):
            self.calls.append(record_id)
            return super().from_store(st, record_id)

    fit = Counting()
    method = LambertianRatio(estimator=fit)
    res = run_benchmark(store, method, BOTH, tmp_path, progress=False, grid_pairs=0, save_images=False,
                        estimator=LightFit())
    pairs = [p for ps in load_pairs(store, BOTH).values() for p in ps]
    sources = {p.source for p in pairs}
    assert len(pairs) > len(sources)  # some record is the source of several pairs: the test can tell
    assert sorted(fit.calls) == sorted(sources)  # one fit per source record
    lights = Lights(store, None)
    for e in [e for e in res.light_errors if e["light"] == "source"][:4]:
        want = lights.error(method.source_light(StoredFace(store, e["from"])), e["from"], e["from"])
        assert e["rel_error"] == pytest.approx(want[0], rel=1e-12)


def test_cli_identity_lambertian_and_table(synth_store, tmp_path):
    from difareli.cli.benchmark import run
    from difareli.cli.table import run as table_run

    results = {}
    for m in ("identity", "lambertian"):
        results[m] = run(_bench_cfg(tmp_path / m, synth_store, f"method={m}", "grid_pairs=2"))
        d = tmp_path / m
        for f in ("metrics_per_image.csv", "summary.md", "summary.csv", "summary.tex", "light_estimation.csv",
                  "comparison_same_subject.png", "comparison_different_subject.png"):
            assert (d / f).is_file(), f
        n_same = len(load_pairs(EncodingStore.open(synth_store), ["same_subject"])["same_subject"])
        assert len(list((d / "relit" / "same_subject").glob("*.png"))) == n_same
        assert "Light estimation" in (d / "summary.md").read_text()
    # Identity reports the target-light error only; Lambertian also its fitted source lights.
    assert {e["light"] for e in results["identity"].light_errors} == {"target"}
    assert {e["light"] for e in results["lambertian"].light_errors} == {"target", "source"}
    same = [e["rel_error"] for e in results["lambertian"].light_errors if e["protocol"] == "same"]
    assert 0 < np.mean(same) < 1  # a fit, but not the stored light
    # Relighting toward the (same person's) target light beats doing nothing.
    t_id, t_lam = results["identity"].table, results["lambertian"].table
    assert t_lam.cells[("lambertian", "same")]["mse"].mean < 0.5 * t_id.cells[("identity", "same")]["mse"].mean

    cfg = compose_train(tmp_path / "table", [f"runs=[{tmp_path / 'identity'},{tmp_path}/lam*]"], config_name="table")
    merged = table_run(cfg)
    assert merged.methods == ["identity", "lambertian"] and merged.protocols == ["same", "different"]
    recs = tables.read_records(tmp_path / "lambertian" / tables.PER_IMAGE_CSV)
    want = np.mean([r.mse for r in recs if r.protocol == "different"])
    assert merged.cells[("lambertian", "different")]["mse"].mean == pytest.approx(want, rel=1e-12)
    text = (tmp_path / "table" / "table.md").read_text()
    assert "| identity |" in text and "(ii) different subject MSE" in text
    assert (tmp_path / "table" / "table.tex").is_file() and (tmp_path / "table" / "table.csv").is_file()


def test_table_rejects_missing_runs(tmp_path):
    from difareli.cli.table import expand_runs

    with pytest.raises(FileNotFoundError):
        expand_runs([str(tmp_path)])
    with pytest.raises(FileNotFoundError):
        expand_runs([str(tmp_path / "*")])


@pytest.mark.slow
def test_diffusion_method_in_merged_table(synth_store, tiny_checkpoint, tmp_path):
    from difareli.cli.benchmark import run
    from difareli.cli.table import run as table_run

    ckpt = tiny_checkpoint("difareli_pp")
    res = run(_bench_cfg(tmp_path / "diff", synth_store, "method=diffusion", f"method.checkpoint={ckpt}",
                         "sampler=ddim", "sampler.steps=3", "limit=2", "runtime.device=cpu"))
    assert {r.method for r in res.records} == {"difareli_pp/ddim-3"} and len(res.records) == 4
    assert all(np.isfinite([r.dssim, r.mse, r.lpips, r.seconds]).all() for r in res.records)
    run(_bench_cfg(tmp_path / "id", synth_store, "method=identity", "limit=2"))
    merged = table_run(compose_train(tmp_path / "t", [f"runs=[{tmp_path}/*]"], config_name="table"))
    assert set(merged.methods) == {"identity", "difareli_pp/ddim-3"}
    assert merged.cells[("difareli_pp/ddim-3", "same")]["mse"].n == 2


@pytest.mark.slow
def test_multirun_cli(synth_store, tmp_path):
    import subprocess

    out = tmp_path / "multi"
    proc = subprocess.run(["difareli-benchmark", "-m", f"store={synth_store}", "method=identity,oracle", "limit=1",
                           "progress=false", f"hydra.sweep.dir={out}"], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "| oracle | **0.0000" in proc.stdout
    assert sorted(p.parent.name for p in out.glob(f"*/{tables.PER_IMAGE_CSV}")) == ["0", "1"]


def test_default_rule_is_paper_and_composite_differs(synth_store, tmp_path):
    import json

    from difareli.cli.benchmark import run

    res = {r: run(_bench_cfg(tmp_path / r, synth_store, "method=identity", "grid_pairs=0",
                             *([] if r == "paper" else [f"metrics.rule={r}"])))
           for r in ("paper", "composite")}
    d = tmp_path / "paper"
    assert "Metrics rule: paper (the authors' evaluator" in (d / "summary.md").read_text()
    assert json.loads((d / "provenance.json").read_text())["metrics rule"] == "paper"
    assert {r.rule for r in tables.read_records(d / tables.PER_IMAGE_CSV)} == {"paper"}
    assert "rule: composite" in (tmp_path / "composite" / "summary.md").read_text()
    a, b = (res[r].table.cells[("identity", "same")] for r in ("paper", "composite"))
    assert a["mse"].mean == pytest.approx(b["mse"].mean, rel=1e-12)  # MSE: one formula
    assert abs(a["dssim"].mean - b["dssim"].mean) > 1e-4
    # The torchmetrics Metrics saw the same scores the table averages.
    for proto in ("same", "different"):
        mean, se, n = res["paper"].metric_stats[proto]["dssim"]
        cell = res["paper"].table.cells[("identity", proto)]["dssim"]
        assert (n, mean) == (cell.n, pytest.approx(cell.mean, rel=1e-12)) and se == pytest.approx(cell.se, rel=1e-9)
    # The saved relit images of the paper-rule run, scored again under composite: the composite run's numbers.
    again = run(_bench_cfg(tmp_path / "re", synth_store, "method=identity", f"rescore={tmp_path / 'paper'}",
                           "metrics.rule=composite"))
    key = lambda r: (r.protocol, r.record_id)  # noqa: E731
    assert sorted((key(r), r.dssim, r.lpips, r.rule) for r in again.records) == sorted(
        (key(r), r.dssim, r.lpips, r.rule) for r in res["composite"].records)
    assert json.loads((tmp_path / "re" / "provenance.json").read_text())["rescored from"] == str(tmp_path / "paper")
    with pytest.raises(Exception, match="metrics.rule='crop'"):
        run(_bench_cfg(tmp_path / "bad", synth_store, "method=identity", "metrics.rule=crop"))
