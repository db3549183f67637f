"""Aggregation (mean ± SE) and Table I rendering from per-image CSVs."""

import csv
import math

import pytest

from difareli.evaluation import tables as T


def test_mean_se_hand_computed():
    # values 1,2,3,4: mean 2.5; sample var = (2.25+0.25+0.25+2.25)/3 = 5/3; SE = sqrt(5/3)/2.
    s = T.mean_se([1.0, 2.0, 3.0, 4.0])
    assert s.n == 4 and s.mean == 2.5
    assert s.se == pytest.approx(math.sqrt(5 / 3) / 2, rel=1e-15)
    assert s.se == pytest.approx(0.6454972243679028, rel=1e-12)
    one = T.mean_se([0.3])
    assert one.mean == 0.3 and one.n == 1 and math.isnan(one.se)
    skip = T.mean_se([1.0, float("nan"), 3.0])
    assert (skip.mean, skip.n) == (2.0, 2) and skip.se == pytest.approx(1.0)
    assert T.mean_se([]).n == 0


def test_csv_round_trip_is_exact(tmp_path):
    recs = [T.Record("DiFaReli++", "same", "s001_l03", 0.1 / 3, 1e-17, 0.2, 0.07),
            T.Record("DiFaReli++", "different", "s002_l03", 0.5, 0.25, 0.125)]
    path = T.write_records(tmp_path / "run" / T.PER_IMAGE_CSV, recs)
    with open(path) as f:
        assert next(csv.reader(f)) == [*T.COLUMNS, "rule"]
    back = T.read_records(path)
    assert back[0] == recs[0] and back[0].rule == "paper"
    assert back[1].dssim == 0.5 and math.isnan(back[1].seconds)


def _fake_run(path, method, rows):
    return T.write_records(path / T.PER_IMAGE_CSV, [T.Record(method, *r) for r in rows]).parent


@pytest.fixture
def two_runs(tmp_path):
    a = _fake_run(tmp_path / "a", "DiFaReli", [
        ("same", "r1", 0.07, 0.012, 0.13, 2.0), ("same", "r2", 0.08, 0.014, 0.15, 4.0),
        ("different", "r1", 0.10, 0.020, 0.16, 3.0), ("different", "r2", 0.09, 0.022, 0.18, 3.0)])
    b = _fake_run(tmp_path / "b", "DiFaReli++_ss", [
        ("different", "r1", 0.08, 0.015, 0.11, 0.1), ("same", "r1", 0.05, 0.007, 0.10, 0.05),
        ("same", "r2", 0.06, 0.009, 0.12, 0.05), ("different", "r2", 0.09, 0.017, 0.12, 0.1)])
    return a, b


def test_merge_runs_groups_method_by_protocol(two_runs):
    table = T.merge_runs(two_runs)
    assert table.methods == ["DiFaReli", "DiFaReli++_ss"]
    assert table.protocols == ["same", "different"]  # (i) before (ii), whatever the file order
    c = table.cells[("DiFaReli", "same")]
    assert c["dssim"].mean == pytest.approx(0.075) and c["dssim"].n == 2
    # two values: SE = |x1 - x2| / 2
    assert c["dssim"].se == pytest.approx(0.005)
    assert c["mse"].se == pytest.approx(0.001)
    assert table.cells[("DiFaReli++_ss", "different")]["lpips"].mean == pytest.approx(0.115)
    assert table.seconds["DiFaReli"].mean == pytest.approx(3.0)
    assert table.seconds["DiFaReli++_ss"].mean == pytest.approx(0.075)
    assert T.merge_runs(two_runs, methods=["DiFaReli++_ss"]).methods == ["DiFaReli++_ss", "DiFaReli"]


def test_merge_rejects_duplicates_and_missing(two_runs, tmp_path):
    with pytest.raises(ValueError, match="duplicate"):
        T.merge_runs([two_runs[0], two_runs[0]])
    with pytest.raises(FileNotFoundError):
        T.merge_runs([tmp_path / "nope"])
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / T.PER_IMAGE_CSV).write_text("method,protocol,dssim\nx,same,0.1\n")
    with pytest.raises(ValueError, match="missing columns"):
        T.merge_runs([bad])


def test_markdown_has_numbers_and_bold_best(two_runs):
    md = T.merge_runs(two_runs).to_markdown()
    lines = md.strip().split("\n\n")[0].splitlines()
    assert lines[0].startswith("| Method | (i) same subject DSSIM | (i) same subject MSE")
    assert lines[0].endswith("(ii) different subject LPIPS | (ii) different subject n | s/img |")
    assert len(lines) == 4
    assert md.strip().splitlines()[-1].startswith("Metrics rule: paper (the authors' evaluator")
    difa, ss = lines[2], lines[3]
    assert "0.0750 ± 0.0050" in difa and "0.0130 ± 0.0010" in difa and "| 3.00 |" in difa
    assert "**0.0550 ± 0.0050**" in ss and "**0.0850 ± 0.0050**" in ss  # (i) and (ii) DSSIM best
    assert "0.0950 ± 0.0050" in difa and "**" not in difa.split("|")[4]  # (ii) DSSIM: loser not bold
    assert difa.count("|") == ss.count("|") == 2 + 8 + 1
    assert difa.split("|")[5].strip() == "2" and difa.split("|")[9].strip() == "2"  # every mean shows its n


def test_latex_table_shape_and_escaping(two_runs):
    tex = T.merge_runs(two_runs).to_latex(caption="Multi-PIE relighting")
    assert r"\begin{tabular}{lcccrcccrc}" in tex
    assert r"\multicolumn{4}{c}{(i) same subject} & \multicolumn{4}{c}{(ii) different subject}" in tex
    assert r"\cmidrule(lr){2-5}\cmidrule(lr){6-9}" in tex
    row = next(line for line in tex.splitlines() if line.startswith("DiFaReli++"))
    assert row.startswith(r"DiFaReli++\_ss & $\mathbf{0.0550} \pm 0.0050$ & $\mathbf{0.0080} \pm 0.0010$")
    assert row.endswith(r"& 0.0750 \\")
    assert row.count("&") == 9 and row.split("&")[4].strip() == "2"
    difa = next(line for line in tex.splitlines() if line.startswith("DiFaReli &"))
    assert r"$0.0750 \pm 0.0050$" in difa and r"\mathbf" not in difa.split("&")[1]


def test_wide_csv_full_precision(two_runs, tmp_path):
    out = tmp_path / "table.csv"
    text = T.merge_runs(two_runs).to_csv(out)
    assert out.read_text() == text
    rows = list(csv.DictReader(text.splitlines()))
    assert rows[0]["method"] == "DiFaReli"
    assert float(rows[0]["same_dssim_mean"]) == pytest.approx(0.075, abs=1e-15)
    assert float(rows[1]["different_mse_se"]) == pytest.approx(0.001, abs=1e-15)
    assert rows[1]["same_n"] == "2" and float(rows[1]["seconds_per_image"]) == pytest.approx(0.075)


def test_single_image_se_renders_na():
    t = T.summarize([T.Record("A", "same", "r1", 0.1, 0.01, 0.2)])
    assert "0.1000 ± n/a" in t.to_markdown()
    assert "–" in t.to_markdown().splitlines()[2]  # unknown seconds


def test_rule_column_legacy_csv_and_no_mixing(tmp_path):
    comp = _fake_run(tmp_path / "c", "B", [("same", "r1", 0.1, 0.01, 0.2)])
    rows = T.read_records(comp / T.PER_IMAGE_CSV)
    assert rows[0].rule == "paper"  # the default rule
    legacy = tmp_path / "legacy"
    legacy.mkdir()
    (legacy / T.PER_IMAGE_CSV).write_text("method,protocol,record_id,dssim,mse,lpips,seconds\n"
                                          "A,same,r1,0.1,0.01,0.2,\n")
    assert T.read_records(legacy / T.PER_IMAGE_CSV)[0].rule == "composite"  # scored before the rules existed
    with pytest.raises(T.TableError, match=r"different metric rules \(composite: e.g. .*legacy.*; paper: e.g."):
        T.merge_runs([legacy, comp])
    t = T.merge_runs([legacy])
    assert t.rule == "composite" and "Metrics rule: composite (both images composited" in t.to_markdown()
    assert "% metrics rule: composite" in t.to_latex() and "(metrics rule: composite)" in t.to_latex(caption="x")
    row = next(csv.DictReader(t.to_csv().splitlines()))
    assert (row["rule"], row["source"]) == ("composite", "measured")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / T.PER_IMAGE_CSV).write_text("method,protocol,record_id,dssim,mse,lpips,seconds,rule\n"
                                       "A,same,r1,0.1,0.01,0.2,,crop\n")
    with pytest.raises(T.TableError, match=r":2: rule 'crop' is not one of paper, composite"):
        T.read_records(bad / T.PER_IMAGE_CSV)


def test_published_rows_are_labelled_never_bold_and_quoted_exactly(two_runs):
    from difareli.evaluation import published

    t = published.add_to(T.merge_runs(two_runs), ["DiFaReli++", "SfSNet"])
    assert t.methods == ["DiFaReli", "DiFaReli++_ss", "DiFaReli++", "SfSNet"]
    c = t.cells[("DiFaReli++", "same")]
    assert (c["dssim"].mean, c["dssim"].se, c["dssim"].n) == (0.0604, 0.0010, 862)
    assert (c["lpips"].mean, c["lpips"].se) == (0.1043, 0.0013)
    d = t.cells[("DiFaReli++", "different")]
    assert (d["mse"].mean, d["mse"].n) == (0.0169, 200) and math.isnan(d["mse"].se)
    assert ("SfSNet", "different") not in t.cells  # the appendix table has protocol (i) only
    md = t.to_markdown()
    line = next(x for x in md.splitlines() if x.startswith("| DiFaReli++ [published]"))
    assert "0.0604 ± 0.0010" in line and "0.0824 ± n/a" in line and "**" not in line and "| 862 |" in line
    sf = next(x for x in md.splitlines() if x.startswith("| SfSNet [published]"))
    assert "0.2918 ± 0.0013" in sf and sf.count("–") == 5  # (ii) DSSIM, MSE, LPIPS, n; s/img
    # the measured best stays bold although the published rows are lower
    assert "**0.0550 ± 0.0050**" in md
    assert "[published]: DiFaReli++, SfSNet: figures quoted from the DiFaReli++ paper (TPAMI 2026) Table I" in md
    rows = {r["method"]: r for r in csv.DictReader(t.to_csv().splitlines())}
    assert rows["DiFaReli++"]["source"].startswith("the DiFaReli++ paper") and rows["DiFaReli"]["source"] == "measured"
    assert r"DiFaReli++ [published] & $0.0604 \pm 0.0010$" in t.to_latex()
    with pytest.raises(ValueError, match="no published Multi-PIE figures for"):
        published.rows(["Ours"])


def test_random_bytes_and_bad_rows_name_the_file_and_a_fix_the_caller_has(two_runs, tmp_path):
    import os

    bad = tmp_path / "bytes"
    bad.mkdir()
    (bad / T.PER_IMAGE_CSV).write_bytes(b"\xb9" + os.urandom(2000))
    with pytest.raises(T.TableError, match=r"metrics_per_image.csv: not a text CSV \(.*\); is it a "
                                           r"metrics_per_image.csv written by difareli-benchmark"):
        T.merge_runs([bad])
    path = two_runs[0] / T.PER_IMAGE_CSV
    lines = path.read_text().splitlines()
    fields = lines[1].split(",")
    fields[T.COLUMNS.index("dssim")] = "nan"
    path.write_text("\n".join([lines[0], ",".join(fields), *lines[2:]]) + "\n")
    # difareli-table has drop_bad_rows; difareli-ablate and rescore (read_records) do not: no key they lack.
    with pytest.raises(T.TableError, match=r":2: dssim=.* is not finite; .*pass drop_bad_rows=true"):
        T.merge_runs([two_runs[0]])
    with pytest.raises(T.TableError) as e:
        T.read_records(path)
    assert str(e.value).endswith("is not finite; fix or remove the row, or rerun the benchmark that wrote it")
