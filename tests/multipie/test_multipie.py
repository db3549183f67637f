"""difareli-multipie on fake Multi-PIE trees made from SynthFaces renders: layout, the authors' pair lists, drawn
protocols, bad trees (one line each), and the store through difareli-benchmark and difareli-table."""

import json
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.evaluation import tables
from difareli.data.encodings import ENCODINGS
from difareli.errors import UserError
from difareli.multipie import build, layout, protocols
from difareli.multipie.layout import Image
from difareli.data.store import EncodingStore

from tests.helpers import HAS_ESTIMATORS, NO_ESTIMATORS, compose_train

pytestmark = pytest.mark.usefixtures("one_thread")
BIN = Path(sys.executable).parent  # the console scripts of this environment


def fake_tree(store: EncodingStore, root: Path) -> dict[str, str]:
    """Write every record's image as a frontal Multi-PIE image: SynthFaces subject k -> subject k+1, light j ->
    illumination j, session 01, recording 01 (neutral). Returns record id -> Multi-PIE stem."""
    names = {}
    for rid in store.ids():
        m = store.meta(rid)
        img = Image(f"{int(m['subject'][1:]) + 1:03d}", "01", "01", f"{int(m['light_index']):02d}")
        path = img.path(root / "data")
        path.parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(path, np.asarray(store.read(rid, ["image"])["image"]))
        names[rid] = img.stem
    return names


class StorePipeline:
    """Stands in for the photo estimators: an image whose pixels are a record's gets that record's encodings
    (what a perfect estimator would give); anything else has "no face"."""

    def __init__(self, store: EncodingStore):
        from difareli.estimators.loading import BadInput

        self.bad, self.store = BadInput, store
        self.encodings = tuple(e for e in store.encodings if not ENCODINGS[e].oracle)
        self.by_pixels = {np.asarray(store.read(r, ["image"])["image"]).tobytes(): r for r in store.ids()}
        self.size, self.min_side, self.max_side = int(store.dims["H"]), 16, 8192

    def dims(self):
        return dict(self.store.dims)

    def process(self, rgb):
        rid = self.by_pixels.get(np.ascontiguousarray(rgb).tobytes())
        if rid is None:
            raise self.bad("no face detected")
        return {k: np.asarray(v) for k, v in self.store.read(rid, self.encodings).items()}, {"faces": 1}, {"notes": []}


@pytest.fixture(scope="module")
def tree(synth_store, tmp_path_factory):
    root = tmp_path_factory.mktemp("multipie") / "Multi-Pie"
    store = EncodingStore.open(synth_store)
    return root, store, fake_tree(store, root)


def _cfg(out, *overrides):
    """conf/multipie.yaml with overrides (it has no paths group: composed without a Hydra runtime)."""
    from hydra import compose, initialize_config_dir

    from difareli.configs import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("multipie", overrides=[f"out_dir={out / 'store'}", "progress=false", *overrides])


def test_names_and_layout(tree, tmp_path):
    img = Image.parse("001_02_01_051_19.png")
    assert (img.subject, img.session, img.recording, img.illumination) == ("001", "02", "01", "19")
    assert img.path(Path("/d")) == Path("/d/session02/multiview/001/01/05_1/001_02_01_051_19.png")
    assert img.under("07").stem == "001_02_01_051_07"
    for bad in ("001_01_01_041_07.png", "1_01_01_051_07.png", "x.png"):
        with pytest.raises(ValueError):
            Image.parse(bad)
    root, store, names = tree
    assert layout.data_dir(root) == layout.data_dir(root / "data") == root / "data"
    found, missing = layout.scan(root / "data", ["01"], ["00", "01", "02"])
    assert sorted(i.stem for i, _ in found) == sorted(names.values()) and len(found) == len(store.ids())
    assert len(missing) == len({i.recording_key for i, _ in found}) and missing[0].startswith("missing: ")
    (tmp_path / "photos").mkdir()
    with pytest.raises(UserError, match=r"not a Multi-PIE tree .*expected <root>/data/sessionNN/multiview/<subject>/"):
        layout.data_dir(tmp_path)


def test_authors_list_format_and_protocol_from_subjects(tmp_path):
    doc = {"pair": {"pair1": {"src": "005_02_01_051_18.png", "dst": "196_03_01_051_01.png",
                              "gt": "005_02_01_051_01.png"},
                    "pair2": {"src": "007_01_01_051_00.png", "dst": "007_01_01_051_12.png"}}}
    (tmp_path / "l.json").write_text(json.dumps(doc))
    t = protocols.read_lists([tmp_path / "l.json"])
    assert [x.protocol for x in t] == ["different_subject", "same_subject"]
    assert t[1].target.stem == "007_01_01_051_12" and t[1].origin == "l.json pair2"  # gt derived from dst
    assert protocols.protocols_doc(t, "x")["different_subject"] == [
        {"source": "005_02_01_051_18", "light_source": "196_03_01_051_01", "target": "005_02_01_051_01"}]
    for bad, msg in (({"pair": {"p": {"src": "005_02_01_051_18.png"}}}, "p is not an object with 'src' and 'dst'"),
                     ({"p": {"src": "a.png", "dst": "b.png"}}, "p: 'a.png' is not a Multi-PIE image name"),
                     ({"p": {"src": "005_02_01_051_18.png", "dst": "196_03_01_051_01.png",
                             "gt": "196_03_01_051_01.png"}},
                      "the ground truth must show the input's person")):
        (tmp_path / "b.json").write_text(json.dumps(bad))
        with pytest.raises(UserError, match=msg):
            protocols.read_lists([tmp_path / "b.json"])


def test_drawn_protocols_follow_their_rule(tree):
    root, store, names = tree
    images = [Image.parse(s) for s in names.values()]
    a = protocols.draw(images, seed=3, same_subject=5, different_subject=7)
    assert a == protocols.draw(images, seed=3, same_subject=5, different_subject=7)  # the seed alone decides
    assert a != protocols.draw(images, seed=4, same_subject=5, different_subject=7)
    same = [t for t in a if t.protocol == "same_subject"]
    diff = [t for t in a if t.protocol == "different_subject"]
    assert (len(same), len(diff)) == (5, 7)
    assert len({t.source.recording_key for t in same}) == 5  # round-robin: five sittings, one pair each
    for t in a:
        assert t.target == t.source.under(t.light_source.illumination) and t.source != t.target
    assert all(t.light_source == t.target for t in same)
    assert all(t.light_source.subject != t.source.subject for t in diff)
    assert len(protocols.draw(images, 0, 10_000, 0)) == 2 * len({i.recording_key for i in images})  # all (i, j)


@pytest.mark.slow  # three console commands end to end: the default run has to finish in minutes at load 4
def test_fake_tree_through_multipie_benchmark_and_table(tree, tmp_path):
    from difareli.cli.benchmark import run as bench
    from difareli.cli.multipie import run
    from difareli.cli.table import run as table_run

    root, store, names = tree
    opts = (f"root={root}", "illuminations=[0,1]", "same_subject=6", "different_subject=6", "images=all")
    report = run(_cfg(tmp_path, *opts), StorePipeline(store))
    assert report.skipped == [] and report.written == 16 and report.pairs == {"same_subject": 6, "different_subject": 6}
    out = EncodingStore.open(tmp_path / "store")
    assert out.store_meta["dataset"] == "multipie" and out.meta("001_01_01_051_00")["illumination"] == "00"
    doc = json.loads((tmp_path / "store" / "protocols.json").read_text())
    assert doc["dataset"] == "multipie" and doc["exact_lights"] is False
    # rerun: everything is kept, the same pairs are drawn
    again = run(_cfg(tmp_path, *opts), StorePipeline(store))
    assert (again.written, again.kept) == (0, 16)
    assert json.loads((tmp_path / "store" / "protocols.json").read_text()) == doc
    for method in ("identity", "lambertian"):
        res = bench(compose_train(tmp_path / method, [f"store={tmp_path / 'store'}", f"method={method}",
                                                       "progress=false", "num_threads=null", "grid_pairs=1"],
                                  config_name="benchmark"))
        assert res.provenance["data set"] == "multipie" and not res.light_errors  # no exact light to compare with
        assert {r.protocol for r in res.records} == {"same", "different"} and len(res.records) == 12
    table = table_run(compose_train(tmp_path / "t", [f"runs=[{tmp_path}/identity,{tmp_path}/lambertian]",
                                                     "published=ours"], config_name="table"))
    assert table.methods == ["identity", "lambertian", "DiFaReli", "DiFaReli++", "DiFaReli++_ss"]
    md = (tmp_path / "t" / "table.md").read_text()
    assert "| DiFaReli++_ss [published] | 0.0590 ± 0.0009 |" in md and "Metrics rule: paper" in md
    with pytest.raises(UserError, match="metrics.rule=composite"):
        bench(compose_train(tmp_path / "c", [f"store={tmp_path / 'store'}", "method=identity", "progress=false",
                                             "num_threads=null", "metrics.rule=composite"], config_name="benchmark"))
        table_run(compose_train(tmp_path / "t2", [f"runs=[{tmp_path}/c]", "published=all"], config_name="table"))
    with pytest.raises(UserError, match="not Multi-PIE"):
        syn = tmp_path / "syn"
        bench(compose_train(syn, [f"store={store.root}", "method=identity", "progress=false", "num_threads=null",
                                  "limit=1"], config_name="benchmark"))
        table_run(compose_train(tmp_path / "t3", [f"runs=[{syn}]", "published=all"], config_name="table"))


def test_bad_tree_one_line_each_and_pairs_dropped(tree, tmp_path, capsys):
    from difareli.cli.multipie import run

    root, store, names = tree
    good = sorted(names.values())
    data = root / "data"
    bad_root = tmp_path / "Multi-Pie"
    for stem in good[:4]:  # subjects 001 and 002 under illuminations 00, 01
        dst = Image.parse(stem).path(bad_root / "data")
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes(Image.parse(stem).path(data).read_bytes())
    unreadable = Image("003", "01", "01", "00").path(bad_root / "data")
    unreadable.parent.mkdir(parents=True)
    unreadable.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    faceless = unreadable.with_name("003_01_01_051_01.png")
    iio.imwrite(faceless, np.full((32, 32, 3), 128, np.uint8))
    pairs = {"pair": {"p1": {"src": good[0], "dst": good[1]}, "p2": {"src": good[1], "dst": good[2]},
                      "p3": {"src": "003_01_01_051_00.png", "dst": "003_01_01_051_01.png"},
                      "p4": {"src": good[2], "dst": "004_01_01_051_00.png"}}}
    (tmp_path / "pairs.json").write_text(json.dumps(pairs))
    report = run(_cfg(tmp_path, f"root={bad_root}", f"pairs={tmp_path / 'pairs.json'}"), StorePipeline(store))
    err = capsys.readouterr().err.splitlines()
    missing = Image("004", "01", "01", "00").path(bad_root / "data")
    assert len(err) == 3 and err[0] == f"skipped {missing}: missing"
    assert err[1].startswith(f"skipped {unreadable}: unreadable (unreadable image (")  # PIL names it variously
    assert err[2] == f"skipped {faceless}: no face (no face detected)"
    assert report.pairs == {"same_subject": 1, "different_subject": 1} and report.dropped == 2
    assert "3 of 6 skipped (1 missing, 1 unreadable, 1 no face)" in report.summary()
    kinds = [s["kind"] for s in json.loads((tmp_path / "store" / build.REPORT).read_text())["skipped"]]
    assert kinds == ["missing", "unreadable", "no face"]


def test_wrong_root_exits_2_naming_the_layout(tmp_path):
    proc = subprocess.run([str(BIN / "difareli-multipie"), f"root={tmp_path}", f"out_dir={tmp_path / 's'}"],
                          capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"difareli-multipie: root={tmp_path}: not a Multi-PIE tree")
    assert "<root>/data/sessionNN/multiview/<subject>/<recording>/05_1/" in lines[0]


@pytest.mark.slow
@pytest.mark.skipif(not HAS_ESTIMATORS, reason=NO_ESTIMATORS)
def test_real_estimators_on_rendered_tree(tmp_path):
    """The photo estimators on 256 px SynthFaces renders laid out as Multi-PIE, a faceless image among them;
    then the benchmark and the table with the published rows."""
    from difareli.synth.generator import generate

    sf = tmp_path / "sf"
    generate(out_dir=str(sf), subjects=4, lights=3, resolution=256, seed=11)
    root = tmp_path / "Multi-Pie"
    fake_tree(EncodingStore.open(sf), root)
    noise = Image("005", "01", "01", "00").path(root / "data")
    noise.parent.mkdir(parents=True)
    iio.imwrite(noise, np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8))
    store = tmp_path / "store"
    proc = subprocess.run([str(BIN / "difareli-multipie"), f"root={root}", f"out_dir={store}", "size=128",
                           "illuminations=[0,1,2]", "same_subject=8", "different_subject=8", "images=all",
                           "progress=false"],
                          capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr[-3000:]  # written, one image skipped
    skipped = [line for line in proc.stderr.splitlines() if line.startswith("skipped ")]
    assert len(skipped) == 3 and skipped[2].startswith(f"skipped {noise}: no face (")  # faceless, named last
    assert skipped[:2] == [f"skipped {noise.with_name(f'005_01_01_051_0{i}.png')}: missing" for i in (1, 2)]
    doc = json.loads((store / "protocols.json").read_text())
    assert doc["same_subject"] and doc["different_subject"]
    for m in ("identity", "lambertian"):
        p = subprocess.run([str(BIN / "difareli-benchmark"), f"store={store}", f"method={m}", "progress=false",
                            f"hydra.run.dir={tmp_path / m}"], capture_output=True, text=True, cwd=tmp_path)
        assert p.returncode == 0, p.stderr[-3000:]
    p = subprocess.run([str(BIN / "difareli-table"), f"runs=[{tmp_path}/identity,{tmp_path}/lambertian]",
                        "published=all", f"hydra.run.dir={tmp_path / 't'}"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    md = (tmp_path / "t" / "table.md").read_text()
    assert "| lambertian |" in md and "DiFaReli++ [published]" in md
    rows = tables.read_records(tmp_path / "lambertian" / tables.PER_IMAGE_CSV)
    assert {r.protocol for r in rows} == {"same", "different"}
