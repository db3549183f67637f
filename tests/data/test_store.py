"""EncodingStore: header checks, atomic/resumable writes, lazy reads, verify()."""

import json
import os
import time

import numpy as np
import pytest

from difareli.data import encodings as E
from difareli.data import store as store_mod
from difareli.data.store import EncodingStore, validate_record_id

DIMS = {"H": 4, "W": 5, "S": 6, "D": 7}
NAMES = ["image", "light", "shape", "identity", "masks", "face_mask", "shading"]


def record(rng, dims=DIMS):
    h, w = dims["H"], dims["W"]
    return {
        "image": rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        "light": rng.normal(size=(9, 3)),  # float64 on purpose: the store casts to float32
        "shape": rng.normal(size=dims["S"]).astype(np.float32),
        "identity": rng.normal(size=dims["D"]).astype(np.float32),
        "masks": rng.integers(0, E.NUM_MASK_PARTS, (h, w), dtype=np.uint8),
        "face_mask": rng.random((h, w)) > 0.5,
        "shading": rng.random((h, w, 3)).astype(np.float32),
    }


@pytest.fixture
def st(tmp_path):
    return EncodingStore.create(tmp_path / "s", DIMS, NAMES, {"generator": {"seed": 3}}, durable=False)


def test_header_and_roundtrip(st, rng, tmp_path):
    arrs = record(rng)
    assert st.write("a-1", arrs, {"split": "train", "subject": "s0", "light_index": np.int64(2)})
    header = json.loads((tmp_path / "s" / "store.json").read_text())
    assert header == {"schema_version": E.SCHEMA_VERSION, "dims": DIMS, "encodings": NAMES,
                      "meta": {"generator": {"seed": 3}}}
    again = EncodingStore.open(tmp_path / "s")
    assert again.ids() == ["a-1"] and len(again) == 1 and "a-1" in again and "zz" not in again
    out = again.read("a-1")
    assert set(out) == set(NAMES)
    for name in NAMES:
        assert out[name].dtype == np.dtype(E.get(name).dtype)
        np.testing.assert_array_equal(out[name], arrs[name].astype(E.get(name).dtype))
    assert again.meta("a-1") == {"split": "train", "subject": "s0", "light_index": 2}
    assert again.available("shading") and not again.available("normal")


def test_read_is_lazy_and_memmapped(st, rng, monkeypatch):
    st.write("r", record(rng))
    opened = []
    real_load = np.load

    def counting_load(file, *a, **k):
        opened.append(os.path.basename(str(file)))
        return real_load(file, *a, **k)

    monkeypatch.setattr(np, "load", counting_load)
    out = st.read("r", ["light", "masks"])
    assert sorted(opened) == ["light.npy", "masks.npy"]
    assert all(isinstance(v, np.memmap) for v in out.values())
    with pytest.raises(ValueError):  # read-only: a dataset can never corrupt the store
        out["light"][0, 0] = 1.0


def test_missing_encoding_and_record_errors(st, rng):
    st.write("r", record(rng))
    (st.records_dir / "r" / "shading.npy").unlink()
    with pytest.raises(KeyError, match=r"'shading'.*'r'.*" + str(st.root.name)):
        st.read("r", ["shading"])
    with pytest.raises(KeyError, match="unknown encoding 'nope'"):
        st.read("r", ["nope"])
    with pytest.raises(KeyError, match="no record 'q'"):
        st.read("q", ["light"])


@pytest.mark.parametrize(
    "name,bad,msg",
    [
        ("light", np.zeros((3, 9), np.float32), "shape"),
        ("image", np.zeros((4, 5, 3), np.float32), "dtype"),
        ("shading", np.full((4, 5, 3), np.nan, np.float32), "NaN"),
    ],
)
def test_validation_names_record_and_encoding(st, rng, name, bad, msg):
    arrs = record(rng)
    arrs[name] = bad
    with pytest.raises(ValueError, match=rf"record 'bad'.*{name}.*{msg}"):
        st.write("bad", arrs)
    assert not st.has("bad") and os.listdir(st.records_dir) == []


def test_unknown_and_missing_encodings_rejected(st, rng):
    arrs = record(rng)
    with pytest.raises(ValueError, match=r"'normal'.*not declared"):
        st.write("x", {**arrs, "normal": np.zeros((4, 5, 3), np.float32)})
    del arrs["masks"]
    with pytest.raises(ValueError, match=r"record 'x': missing encodings \['masks'\]"):
        st.write("x", arrs)
    assert os.listdir(st.records_dir) == []


@pytest.mark.parametrize("rid", ["", ".hidden", "a/b", "../x", "-x", "a b", "x" * 201, "é"])
def test_bad_record_ids(st, rng, rid):
    with pytest.raises(ValueError, match="invalid record id"):
        st.write(rid, record(rng))


def test_good_record_ids():
    for rid in ["00042", "subj_3-light_12", "a.b+c=d", "X" * 200]:
        assert validate_record_id(rid) == rid


@pytest.mark.parametrize("target", ["save", "rename"])
def test_crash_mid_record_leaves_nothing_then_resumes(tmp_path, rng, monkeypatch, target):
    st = EncodingStore.create(tmp_path / "s", DIMS, NAMES, durable=True)
    arrs = record(rng)
    calls = {"n": 0}
    real_save = np.save

    def flaky_save(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:  # die after two encodings hit the disk
            raise KeyboardInterrupt("killed")
        return real_save(*a, **k)

    def flaky_rename(*a, **k):
        raise KeyboardInterrupt("killed")

    if target == "save":
        monkeypatch.setattr(np, "save", flaky_save)
    else:
        monkeypatch.setattr(store_mod.os, "rename", flaky_rename)
    with pytest.raises(KeyboardInterrupt):
        st.write("r0", arrs)
    monkeypatch.undo()
    assert not st.has("r0") and st.ids() == [] and len(EncodingStore.open(tmp_path / "s")) == 0
    assert st.write("r0", arrs)
    assert st.verify() == [] and st.ids() == ["r0"]


def test_stale_tmp_cleaned_only_when_writer_dead(tmp_path, rng):
    st = EncodingStore.create(tmp_path / "s", DIMS, NAMES, durable=False)
    dead = st.records_dir / ".tmp-r1-999999999"  # no such pid
    live = st.records_dir / f".tmp-r2-{os.getppid()}"  # a live process (our parent)
    for d in (dead, live):
        d.mkdir()
        (d / "light.npy").write_bytes(b"partial")
    assert st.ids() == [] and len(st) == 0  # scratch folders never count as records
    EncodingStore.open(tmp_path / "s")  # read-only open touches nothing
    assert dead.exists()
    EncodingStore.open(tmp_path / "s", writable=True)
    assert not dead.exists() and live.exists()


def test_a_store_without_its_records_folder_reads_empty_and_opening_it_creates_nothing(tmp_path, rng):
    # git keeps no empty folder: a cloned empty store has its header only, and may sit on a read-only disk.
    EncodingStore.create(tmp_path / "s", DIMS, NAMES, durable=False).records_dir.rmdir()
    st = EncodingStore.open(tmp_path / "s")
    assert st.ids() == [] and len(st) == 0 and not st.has("r0") and "r0" not in st
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["store.json"]
    assert st.write("r0", record(rng)) and st.ids() == ["r0"]  # a writer makes the folder it needs
    assert EncodingStore.open(tmp_path / "s").ids() == ["r0"]


def test_interrupted_overwrite_restores_old_record(tmp_path, rng):
    st = EncodingStore.create(tmp_path / "s", DIMS, NAMES, durable=False)
    arrs = record(rng)
    st.write("r", arrs)
    os.rename(st.records_dir / "r", st.records_dir / ".old-r-999999999")  # killed between the two renames
    st2 = EncodingStore.open(tmp_path / "s", writable=True)
    assert st2.ids() == ["r"] and st2.verify() == []
    np.testing.assert_array_equal(st2.read("r", ["image"])["image"], arrs["image"])


def test_skip_and_overwrite(st, rng):
    first, second = record(rng), record(rng)
    assert st.write("r", first, {"v": 1})
    assert not st.write("r", second, {"v": 2})  # resume: existing record untouched
    assert st.meta("r") == {"v": 1}
    np.testing.assert_array_equal(st.read("r", ["image"])["image"], first["image"])
    assert st.write("r", second, {"v": 2}, overwrite=True)
    assert st.meta("r") == {"v": 2} and st.ids() == ["r"]
    np.testing.assert_array_equal(st.read("r", ["image"])["image"], second["image"])
    assert sorted(os.listdir(st.records_dir)) == ["r"]  # old copy and scratch removed


def test_create_existing_store(tmp_path, rng):
    root = tmp_path / "s"
    st = EncodingStore.create(root, DIMS, NAMES, durable=False)
    st.write("r", record(rng))
    with pytest.raises(ValueError, match=r"differing dims.*'H': \(4, 8\)"):
        EncodingStore.create(root, {**DIMS, "H": 8}, NAMES)
    with pytest.raises(ValueError, match="exists with encodings"):
        EncodingStore.create(root, DIMS, NAMES[:-1])
    again = EncodingStore.create(root, DIMS, NAMES)  # resume: same header, records kept
    assert again.ids() == ["r"]
    with pytest.warns(UserWarning, match="different meta"):
        EncodingStore.create(root, DIMS, NAMES, {"other": 1})


def test_create_checks_inputs(tmp_path):
    with pytest.raises(ValueError, match="needs dimension 'D'"):
        EncodingStore.create(tmp_path / "a", {"H": 2, "W": 2}, ["identity"])
    with pytest.raises(KeyError, match="unknown encoding 'albedo'"):
        EncodingStore.create(tmp_path / "b", DIMS, ["albedo"])
    with pytest.raises(FileNotFoundError, match="no encoding store"):
        EncodingStore.open(tmp_path / "c")


def test_schema_version_mismatch(tmp_path):
    root = tmp_path / "s"
    EncodingStore.create(root, DIMS, NAMES)
    header = json.loads((root / "store.json").read_text())
    header["schema_version"] = E.SCHEMA_VERSION + 1
    (root / "store.json").write_text(json.dumps(header))
    with pytest.raises(ValueError, match=rf"schema_version {E.SCHEMA_VERSION + 1}.*version {E.SCHEMA_VERSION}"):
        EncodingStore.open(root)


def test_ids_filter_by_split_and_subject(st, rng):
    for i in range(6):
        st.write(f"r{i}", record(rng), {"split": "train" if i % 3 else "test", "subject": f"s{i // 2}"})
    assert st.ids() == [f"r{i}" for i in range(6)]
    assert st.ids(split="test") == ["r0", "r3"]
    assert st.ids(subject="s1") == ["r2", "r3"]
    assert st.ids(split="train", subject="s1") == ["r2"]
    st.write("r9", record(rng), {"split": "test"})  # cached listing and index stay current
    assert st.ids(split="test") == ["r0", "r3", "r9"] and len(st) == 7


def test_verify_finds_broken_records(st, rng):
    for rid in ["ok", "nofile", "badshape", "garbage", "nometa"]:
        st.write(rid, record(rng))
    assert st.verify() == []
    d = st.records_dir
    (d / "nofile" / "masks.npy").unlink()
    np.save(d / "badshape" / "light.npy", np.zeros((3, 9), np.float32))
    (d / "garbage" / "shape.npy").write_bytes(b"not an npy file")
    (d / "nometa" / "meta.json").unlink()
    problems = st.verify()
    assert len(problems) == 4, problems
    joined = "\n".join(problems)
    assert "nofile: missing encoding 'masks'" in joined
    assert "badshape: light has shape (3, 9)" in joined
    assert "garbage: shape unreadable" in joined
    assert "nometa: meta.json unreadable" in joined
    np.save(d / "ok" / "shading.npy", np.full((4, 5, 3), np.inf, np.float32))
    assert st.verify(["ok"]) == [] and "contains NaN or Inf" in st.verify(["ok"], check_values=True)[0]


def test_thousand_small_records(tmp_path, rng):
    st = EncodingStore.create(tmp_path / "s", {"S": 4, "D": 4}, ["light", "shape", "identity"], durable=False)
    arrs = {"light": np.zeros((9, 3), np.float32), "shape": np.ones(4, np.float32), "identity": np.ones(4, np.float32)}
    n = 1000
    t0 = time.perf_counter()
    for i in range(n):
        st.write(f"{i:05d}", arrs, {"split": "train" if i % 2 else "test"})
    t1 = time.perf_counter()
    fresh = EncodingStore.open(tmp_path / "s")
    ids = fresh.ids(split="test")
    t2 = time.perf_counter()
    total = sum(float(fresh.read(rid, ["shape"])["shape"][0]) for rid in fresh.ids())
    t3 = time.perf_counter()
    assert len(fresh) == n and len(ids) == n // 2 and total == n
    print(f"\n{n} records: write {n / (t1 - t0):.0f}/s, list+index {t2 - t1:.3f}s, read {n / (t3 - t2):.0f}/s")
