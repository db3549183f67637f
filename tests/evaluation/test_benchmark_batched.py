"""The benchmark's batched relights (evaluation/batched.py): several pairs per network pass through the relighter's
relight_many, the same relights as pair by pair within the runtime's stated tolerance."""

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from difareli.data.store import EncodingStore
from difareli import errors
from difareli.evaluation.baselines import DiffusionMethod, Identity
from difareli.evaluation.benchmark import run_benchmark
from tests.runtime.test_runtime import BF16_TOL, rel_error

pytestmark = pytest.mark.usefixtures("one_thread")
BOTH = ["same_subject", "different_subject"]


class OneByOne:
    """A model method without relight_many: the benchmark relights it pair by pair (its relighter's cache shares
    a source's inversion between its pairs)."""

    needs_light, needs_light_fit = True, False

    def __init__(self, method: DiffusionMethod):
        self.method, self.name, self.relighter = method, method.name, method.relighter

    def relight(self, *args, **kwargs):
        return self.method.relight(*args, **kwargs)


class Batching(Identity):
    """The input back, pair by pair or through relight_many (batch_size relights a call); ``bad``: the first
    relight_many call fails as a non-finite result would."""

    batch_size = 4

    def __init__(self, bad: bool = False):
        super().__init__("batching")
        self.bad, self.calls, self.single = bad, [], 0

    def relight(self, source, *args, **kwargs):
        self.single += 1
        return super().relight(source, *args, **kwargs)

    def relight_many(self, sources, targets):
        self.calls.append([len(t) for t in targets])
        if self.bad and len(self.calls) == 1:
            raise errors.NonFiniteError("relight of a bad record: NaN")
        return [np.stack([np.array(s.image)] * len(t)) for s, t in zip(sources, targets)]


@pytest.mark.parametrize("bad", [False, True])
def test_pairs_go_through_relight_many_grouped_by_source(synth_store, tmp_path, bad):
    """Each source with its pairs of both protocols, batch_size relights a call, no pair relit twice; a failed call's
    pairs are relit one by one (only a bad pair would fail its row); the rows are the identity's."""
    store = EncodingStore.open(synth_store)
    kw = dict(limit=3, progress=False, grid_pairs=0, save_images=False)
    method = Batching(bad)
    rows = run_benchmark(store, method, BOTH, tmp_path / "b", **kw).records
    want = run_benchmark(store, Identity("batching"), BOTH, tmp_path / "i", **kw).records
    assert [(r.protocol, r.record_id, r.mse, r.dssim) for r in rows] == [
        (r.protocol, r.record_id, r.mse, r.dssim) for r in want]
    assert [len(c) for c in method.calls] == [2, 1] and all(k == 2 for c in method.calls for k in c)
    assert method.single == (4 if bad else 0)  # the first call's 2 sources x 2 pairs
    assert all(r.status == "ok" and r.seconds >= 0 for r in rows)


@pytest.mark.slow
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_batched_relights_equal_pair_by_pair(synth_store, tiny_checkpoint, tmp_path, precision):
    store = EncodingStore.open(synth_store)
    method = DiffusionMethod(tiny_checkpoint("difareli_pp"), {"name": "ddim", "steps": 3},
                             runtime={"device": "cpu", "precision": precision})
    calls = []
    many = method.relighter.relight_many

    def spy(sources, targets, **kw):
        calls.append([len(t) for t in targets])
        return many(sources, targets, **kw)

    method.relighter.relight_many = spy
    kw = dict(limit=3, progress=False, grid_pairs=0)
    batched = run_benchmark(store, method, BOTH, tmp_path / "batched", **kw)
    del method.relighter.relight_many
    single = run_benchmark(store, OneByOne(method), BOTH, tmp_path / "single", **kw)
    sources = sum(len(c) for c in calls)
    # 6 pairs, every source with its pair of each protocol: sources inverted together, 2 targets each
    assert len(batched.records) == len(single.records) == 6 == sources * 2 and calls == [[2, 2, 2]]
    dirs = {"same": "same_subject", "different": "different_subject"}
    worst = 0.0
    for a, b in zip(batched.records, single.records, strict=True):
        assert (a.protocol, a.record_id, a.status, b.status) == (b.protocol, b.record_id, "ok", "ok")
        assert a.seconds > 0
        x, y = (np.asarray(iio.imread(d / "relit" / dirs[a.protocol] / f"{a.record_id}.png"))[..., :3]
                .astype(np.float64) for d in (tmp_path / "batched", tmp_path / "single"))
        if precision == "fp32":  # batch-dependent float sums only: a uint8 step here and there
            assert np.abs(x - y).max() <= 1 and (x != y).mean() < 0.01
        worst = max(worst, rel_error(torch.from_numpy(x), torch.from_numpy(y)))
        for m in ("dssim", "mse", "lpips"):
            assert getattr(a, m) == pytest.approx(getattr(b, m), rel=0.05 if precision == "bf16" else 1e-3, abs=1e-4)
    assert worst < (BF16_TOL if precision == "bf16" else 1e-2)


def test_a_batched_pair_is_scored_from_the_source_its_batch_read(synth_store, tmp_path, monkeypatch):
    """Issue 62: a pair relit in a batch is scored (its extra columns) and drawn in the comparison grid from the
    source record as its batch read and checked it, not from a second read of the record."""
    from difareli.evaluation.extras import PairExtras
    from difareli.utils import viz

    store, method = EncodingStore.open(synth_store), Batching()
    given, scored, drawn = [], [], []
    many, extras, grid = method.relight_many, PairExtras.__call__, viz.grid

    def relight_many(sources, targets):
        given.extend(sources)
        return many(sources, targets)

    def score_extras(self, relit, source, target, light):
        scored.append(source)
        return extras(self, relit, source, target, light)

    method.relight_many = relight_many
    monkeypatch.setattr(PairExtras, "__call__", score_extras)
    monkeypatch.setattr(viz, "grid", lambda rows: drawn.extend(rows) or grid(rows))
    res = run_benchmark(store, method, BOTH, tmp_path, limit=3, progress=False, grid_pairs=1)
    assert [r.status for r in res.records] == ["ok"] * 6 and method.single == 0
    assert len(scored) == 6 and all(any(s is g for g in given) for s in scored)
    assert len(drawn) == 2 and all(any(row[0] is g.image for g in given) for row in drawn)
