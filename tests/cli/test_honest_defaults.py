"""Honest defaults: the target c a user has (target_shadow.target_shadow_of), oracle inputs only behind
oracle_* flags, and the benchmark's tables stating which inputs were used."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from difareli.data import target_shadow
from difareli.evaluation.baselines import Identity
from difareli.evaluation.benchmark import run_benchmark
from difareli.data.store import EncodingStore

pytestmark = pytest.mark.usefixtures("one_thread")


def test_stored_shadow_is_an_estimate_only_where_a_user_would_have_it():
    meta = lambda **m: SimpleNamespace(store_meta=m)  # noqa: E731
    assert target_shadow.stored_shadow_is_estimate(meta(generator="synthfaces", inputs="estimated"))
    assert not target_shadow.stored_shadow_is_estimate(meta(generator="synthfaces", inputs="exact"))
    assert target_shadow.stored_shadow_is_estimate(meta(generator="preprocess"))  # photos: estimators only


def test_target_shadow_of_exact_store_uses_the_stated_policy(synth_store):
    store = EncodingStore.open(synth_store)  # SynthFaces inputs=exact: its stored c is the exact one
    rid = store.ids(split="test")[0]
    c, how = target_shadow.target_shadow_of(store, rid)
    train = [float(store.read(r, ["shadow"])["shadow"][0]) for r in store.ids(split="train")]
    assert c == pytest.approx(target_shadow.typical_shadowed_c(train)) and "median shadowed c" in how
    exact, how = target_shadow.target_shadow_of(store, rid, oracle=True)
    assert exact == float(store.read(rid, ["shadow"])["shadow"][0]) and how == "exact c (oracle)"


@pytest.mark.parametrize("oracle_shadow", [False, True])
def test_benchmark_tables_state_their_inputs(synth_store, tmp_path, oracle_shadow):
    store = EncodingStore.open(synth_store)
    res = run_benchmark(store, Identity(), ["same_subject"], tmp_path, limit=1, progress=False, grid_pairs=0,
                        oracle_shadow=oracle_shadow)
    prov = json.loads(res.paths["provenance"].read_text())
    assert prov["target light"].startswith("fitted")
    want = "exact c (oracle)" if oracle_shadow else target_shadow.target_shadow_of(store, store.ids(split="test")[0])[1]
    assert prov["target c"] == want
    assert res.paths["summary_md"].read_text().startswith("Inputs: target light: fitted")
