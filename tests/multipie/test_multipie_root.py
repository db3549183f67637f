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
