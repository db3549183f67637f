"""Fuzz suite: random corruptions of light files, per-image CSVs and store records must end in an
error naming the input (or, for CSVs with drop_bad_rows, a table whose n says what was left out), never in
silently changed numbers, and must leave what was already written unchanged."""

from __future__ import annotations

import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from difareli.evaluation import tables as T
from difareli.errors import UserError
from difareli.data.store import EncodingStore
from difareli.relight.targets import load_sh_file, target_lights

FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
finite = st.floats(-50, 50, allow_nan=False, allow_infinity=False)
bad_value = st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e30])


# ------------------------------------------------------------------------------------------ light files
@FUZZ
@given(values=st.lists(finite, min_size=27, max_size=27), where=st.integers(0, 26), bad=bad_value,
       as_text=st.booleans())
def test_light_file_with_one_bad_value_is_named(values, where, bad, as_text):
    with tempfile.TemporaryDirectory() as d:
        good = np.array(values).reshape(9, 3)
        path = Path(d) / ("l.txt" if as_text else "l.npy")
        if as_text:
            np.savetxt(path, good.reshape(-1), fmt="%.17g")
        else:
            np.save(path, good)
        np.testing.assert_array_equal(load_sh_file(path), good)  # valid: read back exactly
        broken = good.copy()
        broken.flat[where] = bad
        np.savetxt(path, broken.reshape(-1), fmt="%.17g") if as_text else np.save(path, broken)
        with pytest.raises(UserError, match=f"target light file {path}"):
            load_sh_file(path)


@FUZZ
@given(text=st.text(min_size=0, max_size=60))
def test_light_file_of_text_is_named(text):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "light.txt"
        path.write_text(text)
        try:
            light = load_sh_file(path)
        except UserError as e:
            assert str(e).startswith(f"target light file {path}")
        else:  # only text that really is 27 finite, plausible numbers may load
            assert light.shape == (9, 3) and np.isfinite(light).all()


def test_a_light_file_of_another_layout_is_refused_not_scrambled(tmp_path):
    """Before: a 3x9 array (a transposed light) or 3x3x3 was read row-major as 9x3, another light, exit 0. Issue 64,
    our probe (difareli-relight target.light=light_39.npy)."""
    good = np.arange(27, dtype=np.float64).reshape(9, 3) / 10
    for name, arr, fix in (("t.npy", good.T, "transpose it (light.T)"),
                           ("c.npy", good.reshape(3, 3, 3), "save it as a 9x3 array")):
        np.save(tmp_path / name, arr)
        with pytest.raises(UserError) as e:
            load_sh_file(tmp_path / name)
        shape = "x".join(map(str, arr.shape))
        assert str(e.value) == (f"target light file {tmp_path / name} is a {shape} array; a light is 9x3 (9 SH bands "
                                f"of R, G, B: DECA's order) or 27 numbers in that order: {fix}")
    np.savetxt(tmp_path / "rows.txt", good.T)  # 3 lines of 9
    with pytest.raises(UserError, match="is a 3x9 array; a light is 9x3"):
        load_sh_file(tmp_path / "rows.txt")
    for name, arr in (("a.npy", good), ("b.npy", good.reshape(-1)), ("c.txt", good), ("d.txt", good.reshape(1, -1))):
        np.save(tmp_path / name, arr) if name.endswith(".npy") else np.savetxt(tmp_path / name, arr)
        np.testing.assert_allclose(load_sh_file(tmp_path / name), good)


def test_an_environment_map_of_negative_radiance_is_refused(tmp_path):
    """Before: a map of -1 everywhere relit the photo under an "anti-light" with a warning, exit 0. Issue 64, our
    probe (difareli-relight target.envmap=env_neg.npy)."""
    from difareli.relight.targets import load_envmap

    env = np.ones((16, 32, 3))
    env[2, 3, 1] = -0.25
    np.save(tmp_path / "e.npy", env)
    with pytest.raises(UserError) as e:
        load_envmap(tmp_path / "e.npy")
    assert str(e.value) == (f"environment map {tmp_path / 'e.npy'}: 1 of 1536 values are negative (lowest -0.25); "
                            "radiance is >= 0: save the map unshifted (clip it at 0)")
    env[2, 3, 1] = 0.0
    np.save(tmp_path / "e.npy", env)
    np.testing.assert_array_equal(load_envmap(tmp_path / "e.npy"), env)


@pytest.mark.parametrize("key", ["yaw", "roll"])
def test_nan_rotation_is_named(key):
    # Checked where the request is given (naming the key: test_request); a caller that checked nothing hears of
    # the angle where it turns the light.
    with pytest.raises(UserError, match="rotation angle nan degrees is not finite"):
        target_lights(np.eye(9, 3), **{key: math.nan})
    bad_src = np.eye(9, 3)
    bad_src[0, 0] = np.nan
    with pytest.raises(UserError, match="the source record's light"):
        target_lights(bad_src, **{key: 10.0})


# ------------------------------------------------------------------------------------------ per-image CSVs
ROWS = [("M", "same" if i % 2 else "different", f"r{i}", 0.1 + i / 100, 0.01 * i, 0.2 + i / 50, 0.5) for i in range(8)]


def _write(d: Path) -> Path:
    return T.write_records(d / T.PER_IMAGE_CSV, [T.Record(*r) for r in ROWS])


def _means(table) -> dict:
    return {k: {m: (s.mean, s.n) for m, s in v.items()} for k, v in table.cells.items()}


def _expected(rows) -> dict:
    return _means(T.summarize([T.Record(*r) for r in rows]))


corruption = st.one_of(
    st.tuples(st.just("cut"), st.integers(0, 10_000)),
    st.tuples(st.just("value"), st.integers(0, 7), st.sampled_from(["dssim", "mse", "lpips"]),
              st.sampled_from(["nan", "inf", "-inf", "", "abc", "1e999"])),
    st.tuples(st.just("fields"), st.integers(0, 7), st.integers(-2, 2).filter(bool)),
    st.just(("header_only",)),
)


@FUZZ
@given(c=corruption, drop=st.booleans())
def test_damaged_csv_errors_or_shows_n(c, drop):
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d))
        with open(path, newline="") as f:
            text = f.read()
        lines = text.split("\r\n")
        if c[0] == "cut":
            text = text[: c[1] % (len(text) + 1)]
        elif c[0] == "value":
            fields = lines[1 + c[1]].split(",")
            fields[T.COLUMNS.index(c[2])] = c[3]
            lines[1 + c[1]] = ",".join(fields)
            text = "\r\n".join(lines)
        elif c[0] == "fields":
            fields = lines[1 + c[1]].split(",")
            fields = fields[: c[2]] if c[2] < 0 else fields + ["0.1"] * c[2]
            lines[1 + c[1]] = ",".join(fields)
            text = "\r\n".join(lines)
        else:
            text = lines[0] + "\r\n"
        with open(path, "w", newline="") as f:
            f.write(text)
        before = path.read_bytes()
        try:
            table = T.merge_runs([d], drop_bad_rows=drop)
        except UserError as e:
            assert str(e).startswith(str(path))  # names the file (and the line where one is at fault)
        else:
            parts = text.split("\r\n")
            complete = parts[1:-1] + ([parts[-1][:-1]] if parts[-1].endswith("\r") else [])
            intact = [r for r in ROWS if ",".join(T.record_row(T.Record(*r), status=False)) in complete]
            got = _means(table)
            assert got == _expected(intact)  # every mean is over exactly the intact rows, and says so
            n = sum(max(s.n for s in v.values()) for v in table.cells.values())
            assert n + len(table.dropped) == len(text.rstrip("\r\n").split("\r\n")) - 1 or not drop
            if table.dropped:
                assert f"{len(table.dropped)} bad row(s) dropped" in table.to_markdown()
        assert path.read_bytes() == before  # reading never rewrites a run's CSV


def test_issue_damaged_csvs(tmp_path):
    """The issue's three cases: a row cut inside its last field, nan values, a header-only file."""
    a = _write(tmp_path / "a")
    text = a.read_text()
    a.write_text(text.rstrip("\n")[:-2])  # cut inside the last field
    with pytest.raises(T.TableError, match=rf"{a}:9: .*cut\?"):
        T.merge_runs([a.parent])
    t = T.merge_runs([a.parent], drop_bad_rows=True)
    assert t.cells[("M", "same")]["dssim"].n == 3 and "1 bad row(s) dropped" in t.to_markdown()
    assert "| 3 |" in t.to_markdown() and "| 4 |" in t.to_markdown()
    b = _write(tmp_path / "b")
    b.write_text(b.read_text().replace(repr(0.13), "nan", 1))
    with pytest.raises(T.TableError, match=rf"{b}:5: dssim='nan' is not finite"):
        T.merge_runs([b.parent])
    c = _write(tmp_path / "c")
    c.write_text(c.read_text().splitlines()[0] + "\n")
    with pytest.raises(T.TableError, match=rf"{c}: no usable rows \(0 row\(s\)"):
        T.merge_runs([c.parent])


def test_failed_rows_counted_not_averaged(tmp_path):
    recs = [T.Record(*r) for r in ROWS] + [T.Record("M", "same", "bad", math.nan, math.nan, math.nan, 1.0, "failed")]
    path = T.write_records(tmp_path / T.PER_IMAGE_CSV, recs)
    assert path.read_text().splitlines()[0].endswith(",status")
    table = T.merge_runs([tmp_path])
    assert table.failed == {("M", "same"): 1} and table.cells[("M", "same")]["dssim"].n == 4
    assert _means(table) == _expected(ROWS)
    md = table.to_markdown()
    assert "| 4 (+1 failed) |" in md and "1 relight(s) failed" in md
    assert "same_failed" in table.to_csv()


# ------------------------------------------------------------------------------------------ store records
@pytest.fixture(scope="module")
def store_copy(synth_store, tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzzstore") / "s"
    shutil.copytree(synth_store, root)
    return root


@FUZZ
@given(rid=st.sampled_from(["s00000_l0", "s00003_l1", "s00007_l0"]),
       name=st.sampled_from(["shape", "light", "normal", "image", "shadow"]), keep=st.floats(0, 0.99))
def test_truncated_npy_names_record_and_encoding(store_copy, rid, name, keep):
    file = store_copy / "records" / rid / f"{name}.npy"
    good = file.read_bytes()
    try:
        file.write_bytes(good[: int(len(good) * keep)])
        store = EncodingStore.open(store_copy)
        with pytest.raises(UserError, match=f"record '{rid}', encoding '{name}' in store {store_copy}"):
            store.read(rid, [name])
        assert any(p.startswith(f"{rid}: {name}") for p in store.verify([rid], check_values=True))
    finally:
        file.write_bytes(good)


@FUZZ
@given(name=st.sampled_from(["shape", "light", "normal", "shading", "shadow"]), where=st.integers(0, 10**6),
       bad=st.sampled_from([math.nan, math.inf]))
def test_nonfinite_record_never_committed(store_copy, name, where, bad):
    """What difareli-synth / difareli-preprocess write goes through EncodingStore.write, which validates values
    before the record is renamed into place: nothing is written, the store is unchanged."""
    store = EncodingStore.open(store_copy, writable=True, durable=False)
    arrays = {k: np.array(v) for k, v in store.read("s00001_l0").items()}
    arrays[name].flat[where % arrays[name].size] = bad
    before = sorted(p.name for p in (store_copy / "records").iterdir())
    with pytest.raises(ValueError, match=f"record 'new_one': encoding '{name}': contains NaN or Inf"):
        store.write("new_one", arrays, {"split": "train"})
    assert sorted(p.name for p in (store_copy / "records").iterdir()) == before


def test_wrong_shape_encoding_named(store_copy):
    file = store_copy / "records" / "s00002_l0" / "shape.npy"
    good = file.read_bytes()
    try:
        np.save(file, np.zeros(7, np.float32))
        with pytest.raises(UserError, match="record 's00002_l0', encoding 'shape' .* has shape \\(7,\\)"):
            EncodingStore.open(store_copy).read("s00002_l0", ["shape"])
    finally:
        file.write_bytes(good)
