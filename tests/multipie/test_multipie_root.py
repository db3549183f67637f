"""difareli-multipie records the Multi-PIE copy a store was built from and refuses to resume it from another one
(before: the kept records were the first copy's while the report named the second); a pair whose src and dst
are the same image is refused."""

from __future__ import annotations

import json
import shutil

import pytest

from difareli.data.store import EncodingStore
from difareli.errors import UserError
from difareli.multipie import protocols

from tests.multipie.test_multipie import StorePipeline, _cfg, fake_tree

pytestmark = pytest.mark.usefixtures("one_thread")
OPTS = ("illuminations=[0,1]", "same_subject=2", "different_subject=2", "images=used")


@pytest.fixture(scope="module")
def copies(synth_store, tmp_path_factory):
    base = tmp_path_factory.mktemp("mp_copies")
    store = EncodingStore.open(synth_store)
    fake_tree(store, base / "first")
    shutil.copytree(base / "first", base / "corrected")
    return base / "first", base / "corrected", store


def test_rerun_from_another_copy_is_refused_naming_both(copies, tmp_path):
    from difareli.cli.multipie import run

    first, corrected, store = copies
    report = run(_cfg(tmp_path, f"root={first}", *OPTS), StorePipeline(store))
    assert report.written > 0
    meta = json.loads((tmp_path / "store" / "store.json").read_text())["meta"]
    assert meta["multipie_root"] == str((first / "data").resolve())
    again = run(_cfg(tmp_path, f"root={first / 'data'}", *OPTS), StorePipeline(store))  # same copy: resumes
    assert again.kept == report.written and again.written == 0
    records = sorted(p.name for p in (tmp_path / "store").rglob("*") if p.is_file())
    with pytest.raises(UserError) as e:
        run(_cfg(tmp_path, f"root={corrected}", *OPTS), StorePipeline(store))
    msg = str(e.value)
    assert f"was built from the Multi-PIE copy at {(first / 'data').resolve()}" in msg
    assert f"not root={(corrected / 'data').resolve()}" in msg and "give a new out_dir" in msg
    assert len(msg.splitlines()) == 1
    assert sorted(p.name for p in (tmp_path / "store").rglob("*") if p.is_file()) == records  # nothing touched


def test_store_without_a_recorded_root_is_not_resumed(copies, tmp_path):
    from difareli.cli.multipie import run

    first, _, store = copies
    run(_cfg(tmp_path, f"root={first}", *OPTS), StorePipeline(store))
    header = tmp_path / "store" / "store.json"
    doc = json.loads(header.read_text())
    del doc["meta"]["multipie_root"]
    header.write_text(json.dumps(doc))
    with pytest.raises(UserError, match="records no Multi-PIE copy it was built from"):
        run(_cfg(tmp_path, f"root={first}", *OPTS), StorePipeline(store))


def test_same_image_pair_is_refused(tmp_path):
    doc = {"pair": {"pair1": {"src": "007_01_01_051_00.png", "dst": "007_01_01_051_12.png"},
                    "pair2": {"src": "007_01_01_051_03.png", "dst": "007_01_01_051_03.png"}}}
    (tmp_path / "l.json").write_text(json.dumps(doc))
    with pytest.raises(UserError) as e:
        protocols.read_lists([tmp_path / "l.json"])
    assert str(e.value) == (f"pairs={tmp_path / 'l.json'}: pair2: src and dst are the same image 007_01_01_051_03; a "
                            "pair takes the light of another image: fix the list (dst another illumination or "
                            "subject)")


def test_a_pair_list_nested_too_deeply_is_one_line(tmp_path):
    """Before: a RecursionError traceback (issue 64, our probe: pairs=<a file of 100,000 nested brackets>)."""
    (tmp_path / "l.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(UserError) as e:
        protocols.read_lists([tmp_path / "l.json"])
    assert str(e.value) == (f"pairs={tmp_path / 'l.json'}: nests arrays or objects too deeply to be a pair list; give "
                            "the authors' list file")


def test_recordings_and_illuminations_that_are_no_codes_or_absent_are_one_line(copies, tmp_path):
    """Text where a recording number goes (before: a ValueError traceback, and recordings="01" read as 00 and 01),
    an illumination Multi-PIE does not have, and one the copy lacks (before: one "missing" line per recording and
    exit 1) are each one line naming the option, before any store is made."""
    from difareli.cli.multipie import run

    first, _, store = copies
    cases = {"recordings=abc": "recordings='abc': 'abc' is not a Multi-PIE recording (its recordings are 01-99); give "
                               "numbers, e.g. recordings=[1]",
             "recordings=[1,x]": "recordings=[1, 'x']: 'x' is not a Multi-PIE recording",
             "illuminations=[0,25]": "illuminations=[0, 25]: 25 is not a Multi-PIE illumination (its illuminations "
                                     "are 00-19); give numbers, e.g. illuminations=[1,2,3]",
             "illuminations=[]": "illuminations=[] names none; give at least one, e.g. illuminations=[1,2,3]",
             "illuminations=[0,7]": "illuminations=[0, 7]: illumination(s) 07 are in none of the copy's recording "
                                    "folders (its recording folders hold illumination(s) 00, 01); give illuminations "
                                    "the copy has, or illuminations=null for all of them"}
    for override, want in cases.items():
        opts = [o for o in OPTS if not o.startswith(override.split("=")[0])]
        with pytest.raises(UserError) as e:
            run(_cfg(tmp_path, f"root={first}", *opts, override), StorePipeline(store))
        assert str(e.value).startswith(want) and "\n" not in str(e.value), (override, str(e.value))
        assert not (tmp_path / "store").exists(), override
    from difareli.multipie import layout

    assert layout.codes("01", "recordings", layout.RECORDINGS) == ["01"]  # one code, not the digits 0 and 1
    assert layout.codes([1, "02", 1], "recordings", layout.RECORDINGS) == ["01", "02"]
