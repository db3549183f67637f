"""difareli-table label=: two runs of one method (two checkpoints, two step counts) told apart by a label per run
dir, and refused without one; labels through the summary, paired= and strata=."""

import json
import subprocess
import sys

import numpy as np
import pytest

from difareli.errors import UserError
from difareli.evaluation import paired as P
from difareli.evaluation import tables as T

A = np.linspace(0.1, 0.3, 12)  # DSSIM of the first run on pairs p000..p011


def _run(path, method, values, protocol="same", ids=None, shard=None):
    """A run dir of ``method`` with DSSIM ``values`` (MSE their squares), light categories sun/dim alternating."""
    ids = ids or [f"p{i:03d}" for i in range(len(values))]
    rows = [T.Record(method, protocol, rid, float(v), float(v) ** 2, 0.1, 1.0,
                     info={"light_category": ["sun", "dim"][i % 2]}) for i, (rid, v) in enumerate(zip(ids, values))]
    T.write_records(path / T.PER_IMAGE_CSV, rows)
    if shard is not None:  # a shard marker as difareli.data.shard.write_marker writes it
        (path / "shard.json").write_text(json.dumps({"shard": shard, "job": {"method": method}}))
    return path


def test_two_runs_of_one_method_are_refused_without_labels(tmp_path):
    a = _run(tmp_path / "ck604", "DiFaReli++", A)
    b = _run(tmp_path / "ck8212", "DiFaReli++", A + 0.01)
    # the same pairs (before: "duplicate record") and other pairs (before: silently one row) alike
    c = _run(tmp_path / "other_store", "DiFaReli++", A, ids=[f"q{i}" for i in range(12)])
    for runs in ([a, b], [a, c]):
        with pytest.raises(T.TableError, match=r"both hold method DiFaReli\+\+ \(same\), which would merge into one "
                                               r"row; use label= .*label=\[ck604,"):
            T.merge_runs(runs)
    with pytest.raises(T.TableError, match=r"duplicate run dir"):
        T.merge_runs([a, tmp_path / "." / "ck604"])  # one run listed twice, however spelled
    # one method whose protocols were benchmarked in two runs is one row, as before
    d = _run(tmp_path / "different", "DiFaReli++", A + 0.02, protocol="different")
    t = T.merge_runs([a, d])
    assert t.methods == ["DiFaReli++"] and t.protocols == ["same", "different"]


def test_labels_make_two_rows_and_reach_paired_and_strata(tmp_path):
    a = _run(tmp_path / "a", "DiFaReli++", A)
    b = _run(tmp_path / "b", "DiFaReli++", A + 0.01)
    t, records = T.merge_runs([a, b], labels=["pp_604", "pp_8212"], with_records=True)
    assert t.methods == ["pp_604", "pp_8212"]
    assert t.cells[("pp_604", "same")]["dssim"].mean == pytest.approx(0.2, abs=1e-15)  # mean of linspace(0.1, 0.3)
    assert t.cells[("pp_8212", "same")]["dssim"].mean == pytest.approx(0.21, abs=1e-15)
    assert f"pp_604 = DiFaReli++ ({a})" in t.to_markdown() and "| pp_8212 |" in t.to_markdown()
    (c,) = P.compare(records, ["dssim"], n_boot=200)[0]
    assert (c.a, c.b, c.n) == ("pp_604", "pp_8212", 12) and c.mean == pytest.approx(0.01, abs=1e-12)
    s = T.merge_runs([a, b], labels=["pp_604", "pp_8212"], strata="light_category")
    assert s.methods == ["pp_604", "pp_8212"] and s.cells[("pp_8212", "same | light_category=sun")]["dssim"].n == 6
    # methods= orders the labelled rows
    assert T.merge_runs([a, b], labels=["x", "y"], methods=["y"]).methods == ["y", "x"]


def test_bad_labels_name_the_input_and_the_fix(tmp_path):
    a = _run(tmp_path / "a", "M", A)
    b = _run(tmp_path / "b", "M", A)
    with pytest.raises(T.TableError, match=r"label=\['x'\]: 1 label\(s\) for 2 run dir\(s\) .*give one label per run "
                                           r"dir, in the order of runs="):
        T.merge_runs([a, b], labels=["x"])
    with pytest.raises(T.TableError, match=r"'x' is given to two runs; give each run dir its own label"):
        T.merge_runs([a, b], labels=["x", "x"])
    with pytest.raises(T.TableError, match="an empty label"):
        T.merge_runs([a, b], labels=["x", " "])
    both = tmp_path / "both"
    T.write_records(both / T.PER_IMAGE_CSV, T.read_records(a / T.PER_IMAGE_CSV)
                    + [T.Record("N", "same", "p000", 0.1, 0.01, 0.1)])
    with pytest.raises(T.TableError, match=r"run dir .*both holds 2 methods \['M', 'N'\], and a label names one"):
        T.merge_runs([both], labels=["x"])


def test_shards_of_one_job_are_one_run(tmp_path):
    ids = [f"p{i:03d}" for i in range(12)]
    s0 = _run(tmp_path / "s0", "M", A[:5], ids=ids[:5], shard="0/2")
    s1 = _run(tmp_path / "s1", "M", A[5:], ids=ids[5:], shard="1/2")
    assert T.merge_runs([s0, s1]).cells[("M", "same")]["dssim"].n == 12  # merged without labels, as before
    t = T.merge_runs([s0, s1, _run(tmp_path / "other", "M", A + 0.01)], labels=["sharded", "sharded", "whole"])
    assert t.methods == ["sharded", "whole"] and t.cells[("sharded", "same")]["dssim"].mean == pytest.approx(0.2)
    with pytest.raises(T.TableError, match="give every shard of one job the same label"):
        T.merge_runs([s0, s1], labels=["x", "y"])


def _cfg(out, runs, *extra):
    from tests.helpers import compose_train

    return compose_train(out, [f"runs=[{','.join(str(r) for r in runs)}]", f"out={out}", *extra],
                         config_name="table")


def test_table_cli_label_with_paired_and_strata(tmp_path):
    from difareli.cli.table import run

    a = _run(tmp_path / "a", "DiFaReli++", A)
    b = _run(tmp_path / "b", "DiFaReli++", A + 0.01)
    t = run(_cfg(tmp_path / "o", [a, b], "label=[pp_604,pp_8212]", "strata=light_category", "n_boot=200"))
    assert t.methods == ["pp_604", "pp_8212"]
    text = (tmp_path / "o" / "paired.md").read_text()
    assert "| (i) same subject, light_category=dim | DSSIM | pp_604 | pp_8212 | 6 | +0.01 | [+0.01, +0.01] |" in text
    assert "significant: (i) same subject, light_category=dim DSSIM: pp_604 better than pp_8212" in text
    for bad, why in (("label=[x]", r"1 label\(s\) for 2 run dir"), ("label={k: v}", "give one name per run dir")):
        with pytest.raises(UserError, match=why):
            run(_cfg(tmp_path / "x", [a, b], bad))


def test_table_cli_refuses_a_collision_in_one_line(tmp_path):
    a = _run(tmp_path / "a", "DiFaReli++", A)
    b = _run(tmp_path / "b", "DiFaReli++", A + 0.01)
    p = subprocess.run([sys.executable, "-m", "difareli.cli.table", f"runs=[{a},{b}]", f"out={tmp_path / 'o'}"],
                       capture_output=True, text=True, timeout=300, check=False)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    (line,) = p.stderr.strip().splitlines()
    assert line.startswith("difareli-table: run dirs") and "use label=" in line


def test_runs_that_are_no_run_dirs_are_named_as_what_they_are(tmp_path):
    """Before (issue 64, our probe): a missing path, a file and an encodings store were all "no
    metrics_per_image.csv in run dir <p>" (no fix), and runs=[] wrote an empty table with exit 0."""
    from difareli.cli.table import run

    a = _run(tmp_path / "multi" / "0", "DiFaReli++", A)
    (tmp_path / "f").write_text("x")
    (tmp_path / "store").mkdir()
    (tmp_path / "store" / "store.json").write_text("{}")
    (tmp_path / "empty").mkdir()
    fix = "give difareli-benchmark run dirs (each holds metrics_per_image.csv) or a glob of them"
    for runs, want in (
            ([tmp_path / "nope"], f"runs: {tmp_path / 'nope'} does not exist; {fix}"),
            ([tmp_path / "f"], f"runs: {tmp_path / 'f'} is a file, not a run dir; {fix}"),
            ([tmp_path / "store"], f"runs: {tmp_path / 'store'} is an encodings store, not a benchmark run dir; "
                                   f"benchmark it first (difareli-benchmark store={tmp_path / 'store'} "
                                   "method=<method>) and give that run's out_dir"),
            ([tmp_path / "multi"], f"runs: {tmp_path / 'multi'} holds run dirs (0), not a per-image CSV itself; "
                                   f"give '{tmp_path / 'multi'}/*'"),
            ([tmp_path / "empty"], f"runs: {tmp_path / 'empty'} holds no metrics_per_image.csv, so no benchmark "
                                   f"finished there; {fix}"),
            ([], "runs=[] names no run dir; give difareli-benchmark run dirs or a glob of them, e.g. "
                 "'runs=[logs/a,logs/b]'")):
        with pytest.raises(UserError) as e:
            run(_cfg(tmp_path / "o", runs))
        assert str(e.value) == want
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())  # no table written
    assert run(_cfg(tmp_path / "o", [a])).methods == ["DiFaReli++"]


def test_a_run_dir_json_nested_too_deeply_is_read_as_unrecorded(tmp_path):
    """Before: a benchmark_settings.json of 100,000 nested brackets in a run dir was a RecursionError traceback in
    difareli-table's paired check (fileio.read_json_mapping caught OSError and ValueError only)."""
    from difareli.cli.table import run

    a = _run(tmp_path / "a", "DiFaReli++", A)
    b = _run(tmp_path / "b", "DiFaReli", A + 0.01)
    (a / "benchmark_settings.json").write_text("[" * 100_000 + "]" * 100_000)
    assert run(_cfg(tmp_path / "o", [a, b], "n_boot=200")).methods == ["DiFaReli++", "DiFaReli"]
    assert "| (i) same subject | DSSIM | DiFaReli++ | DiFaReli | 12 |" in (tmp_path / "o" / "paired.md").read_text()
