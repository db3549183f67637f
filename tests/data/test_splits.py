"""Subject splits and protocol pair lists (SPEC 11)."""

import json

import pytest

from difareli.data import protocols as sp


def test_splits_disjoint_complete_deterministic():
    a = sp.assign_splits(101, {"train": 0.8, "val": 0.1, "test": 0.1}, group_size=2, seed=3)
    b = sp.assign_splits(101, {"train": 0.8, "val": 0.1, "test": 0.1}, group_size=2, seed=3)
    assert a == b
    sets = [set(v) for v in a.values()]
    assert sum(len(s) for s in sets) == 101 and set.union(*sets) == set(range(101))
    # 51 groups: round(5.1) = 5 groups each for val/test (the last group is a single subject).
    assert len(a["test"]) in (9, 10) and len(a["val"]) in (9, 10)
    # Whole light groups stay together.
    for name, subs in a.items():
        for s in subs:
            partner = s ^ 1
            if partner < 101:
                assert partner in subs, (name, s)
    assert sp.assign_splits(101, {"train": 0.8, "val": 0.1, "test": 0.1}, 2, seed=4) != a


def test_tiny_data_set_still_has_test_and_val():
    s = sp.assign_splits(6, {"train": 0.9, "val": 0.05, "test": 0.05}, group_size=2, seed=0)
    assert [len(s[k]) for k in sp.SPLITS] == [2, 2, 2]


def test_bad_fractions_raise():
    with pytest.raises(ValueError, match="unknown split"):
        sp.assign_splits(10, {"training": 1.0}, 2, 0)
    with pytest.raises(ValueError, match="fractions"):
        sp.assign_splits(10, {"train": -1.0, "test": 0.5}, 2, 0)


def test_protocol_pairs():
    pairs = sp.protocol_pairs([4, 5, 9], lights=3, group_size=2)
    same, diff = pairs["same_subject"], pairs["different_subject"]
    assert len(same) == 3 * 3 * 2  # 3 subjects x ordered light pairs i != j
    # Subject 9's partner (8) is not a test subject: only 4 <-> 5 give different-subject pairs.
    assert len(diff) == 2 * 3 * 2
    for p in same:
        assert p["light_source"] == p["target"] and p["source"] != p["target"]
        assert p["source"][:6] == p["target"][:6]
    for p in diff:
        src_subj, light_subj = p["source"][:6], p["light_source"][:6]
        assert src_subj != light_subj and p["target"][:6] == src_subj
        assert p["light_source"][-2:] == p["target"][-2:]  # same light index -> same light (one group)
    assert {"source": "s00004_l0", "light_source": "s00005_l2", "target": "s00004_l2"} in diff


def test_write_split_files(tmp_path):
    splits = sp.assign_splits(8, {"train": 0.5, "val": 0.25, "test": 0.25}, 2, 0)
    f1, f2 = sp.write_split_files(tmp_path, splits, lights=2, group_size=2, seed=0)
    doc = json.loads(f1.read_text())
    assert doc["splits"]["test"] == [sp.subject_name(s) for s in splits["test"]]
    proto = json.loads(f2.read_text())
    assert len(proto["same_subject"]) == 2 * 2 and len(proto["different_subject"]) == 2 * 2
    assert sp.record_id(42, 2) == "s00042_l2"
