"""A store without the pairs a benchmark asks for is named by its cause (issue 64, our probe): a store of 2 subjects
(difareli-synth subjects=2 lights=2) has one light group, all in train, so protocols.json lists no pairs. Before:
"has no pairs for protocol 'same_subject' (a test split with light groups of >= 2 subjects is needed for
different_subject)", the other protocol's condition for the asked one's cause."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from difareli.errors import UserError
from difareli.evaluation.pairs import load_pairs

PAIR = {"source": "s00000_l0", "light_source": "s00000_l1", "target": "s00000_l1"}


def _store(tmp_path, test, same, different):
    (tmp_path / "splits.json").write_text(json.dumps({"splits": {"train": ["s00001", "s00002"], "val": [],
                                                                 "test": test}}))
    (tmp_path / "protocols.json").write_text(json.dumps({"same_subject": same, "different_subject": different}))
    return SimpleNamespace(root=str(tmp_path))


def test_an_empty_test_split_is_said_with_the_store_to_make(tmp_path):
    store = _store(tmp_path, [], [], [])
    with pytest.raises(UserError) as e:
        load_pairs(store, ["same_subject", "different_subject"])
    assert str(e.value) == (f"{tmp_path / 'protocols.json'} has no same_subject pairs: its test split is empty "
                            "(splits.json: 2 subject(s), all in train or val; a test split needs 3 or more light "
                            "groups); make the store with more subjects, e.g. difareli-synth subjects=8 lights=2")


def test_a_protocol_without_pairs_names_its_own_cause_and_the_other(tmp_path):
    store = _store(tmp_path, ["s00000"], [PAIR], [])
    with pytest.raises(UserError) as e:
        load_pairs(store, ["same_subject", "different_subject"])
    assert str(e.value) == (f"{tmp_path / 'protocols.json'} has no different_subject pairs: its test split has no "
                            "light group of 2 or more subjects; make the store with light_group_size=2 or more, or "
                            "benchmark the other alone: protocols=[same_subject]")
    assert [p.source for p in load_pairs(store, ["same_subject"])["same_subject"]] == ["s00000_l0"]
    store = _store(tmp_path, ["s00000"], [], [PAIR])
    with pytest.raises(UserError, match="no same_subject pairs: its test subjects have one light each; make the "
                                        r"store with lights=2 or more, or benchmark the other alone: "
                                        r"protocols=\[different_subject\]$"):
        load_pairs(store, ["same_subject", "different_subject"])


@pytest.mark.parametrize("text,why", [('{"same_subject": [', "JSONDecodeError"),
                                      ("[" * 100_000 + "]" * 100_000, "RecursionError"), ("[1]", "a JSON list")])
def test_a_corrupt_pair_file_is_one_line(tmp_path, text, why):
    """Before: a JSONDecodeError or RecursionError traceback from difareli-benchmark (a list: an AttributeError)."""
    store = _store(tmp_path, ["s00000"], [PAIR], [])
    (tmp_path / "protocols.json").write_text(text)
    with pytest.raises(UserError) as e:
        load_pairs(store, ["same_subject"])
    assert str(e.value) == (f"{tmp_path / 'protocols.json'} is not the object of pair lists the store's writer made "
                            f"({why}): corrupt; write the store's pairs again (rerun the difareli-synth or "
                            "difareli-multipie command that made it) or restore the file")
