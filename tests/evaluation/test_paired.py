"""Paired comparisons (mean difference, bootstrap CI, Wilcoxon p), strata, difareli-table's paired= / strata= /
published= checks."""

import math

import numpy as np
import pytest

from difareli.errors import UserError
from difareli.evaluation import paired as P
from difareli.evaluation import tables as T


def _rows(method, values, protocol="same", extra=None, info=None):
    return [T.Record(method, protocol, f"p{i:03d}", float(v), float(v) ** 2, 0.1, 1.0,
                     extra=(extra or {}).copy(), info={**(info(i) if info else {})}) for i, v in enumerate(values)]


def test_constant_shift_collapses_the_ci_and_is_significant():
    a = np.random.default_rng(1).uniform(0.1, 0.3, 40)
    rows, notes = P.compare(_rows("A", a) + _rows("B", a + 0.01), ["dssim"], n_boot=2000, seed=3)
    (c,) = rows
    assert (c.a, c.b, c.n, notes) == ("A", "B", 40, [])
    assert c.mean == pytest.approx(0.01, abs=1e-12)
    assert c.lo == pytest.approx(0.01, abs=1e-12) and c.hi == pytest.approx(0.01, abs=1e-12)
    assert c.p < 1e-6  # every difference has the same sign
    # identical methods: difference 0, no test
    same, _ = P.compare(_rows("A", a) + _rows("C", a), ["dssim"], n_boot=100)
    assert same[0].mean == 0 and math.isnan(same[0].p)


def test_independent_noise_without_shift_covers_zero_and_is_seeded():
    rng = np.random.default_rng(7)
    base = rng.uniform(0.2, 0.4, 200)
    rows = _rows("A", base + rng.normal(0, 0.02, 200)) + _rows("B", base + rng.normal(0, 0.02, 200))
    (c,) = P.compare(rows, ["dssim"], n_boot=4000, seed=0)[0]
    assert c.lo < 0 < c.hi and c.p > 0.05
    # the half-width is about 1.96 standard errors of the mean difference
    d = np.array([r.dssim for r in rows[200:]]) - np.array([r.dssim for r in rows[:200]])
    assert (c.hi - c.lo) / 2 == pytest.approx(1.96 * d.std(ddof=1) / math.sqrt(200), rel=0.1)
    assert P.compare(rows, ["dssim"], n_boot=4000, seed=0)[0] == [c]  # seeded: the same CI again


def test_duplicated_rows_and_mismatched_pairs_are_refused():
    a = _rows("A", [0.1, 0.2, 0.3])
    with pytest.raises(UserError, match="A has two rows for same pair p001"):
        P.compare(a + [a[1]] + _rows("B", [0.1, 0.2, 0.3]), ["dssim"])
    b = _rows("B", [0.1, 0.2, 0.3, 0.4])
    with pytest.raises(UserError, match=r"A and B were scored on different same pairs \(0 only in A.*1 only in B, "
                                        r"e.g. \['p003'\]"):
        P.compare(a + b, ["dssim"])
    rows, notes = P.compare(a + b, ["dssim"], strict=False)
    assert rows == [] and "not compared: A and B" in notes[0]


def test_undefined_scores_leave_the_pair_out_of_that_metric():
    a = _rows("A", [0.1, 0.2, 0.3], extra={"shadow_iou": 0.5})
    b = _rows("B", [0.2, 0.3, 0.4], extra={"shadow_iou": 0.7})
    b[0] = T.Record("B", "same", "p000", 0.2, 0.04, 0.1, 1.0, extra={"shadow_iou": math.nan})
    rows = {c.metric: c for c in P.compare(a + b, ["dssim", "shadow_iou"], n_boot=100)[0]}
    assert rows["dssim"].n == 3 and rows["shadow_iou"].n == 2
    assert rows["shadow_iou"].mean == pytest.approx(0.2)


def test_stratify_by_light_category_and_shadow_share():
    info = lambda i: {"light_category": ["sun", "dim"][i % 2], "shadow_share": repr(0.02 + 0.1 * i)}  # noqa: E731
    rows = _rows("A", [0.1, 0.2, 0.3, 0.4], info=info)
    t = T.summarize(P.stratify(rows, "light_category"))
    assert t.protocols == ["same | light_category=dim", "same | light_category=sun"]
    assert t.cells[("A", "same | light_category=sun")]["dssim"].mean == pytest.approx(0.2)
    by = {r.record_id: r.protocol for r in P.stratify(rows, "shadow_share")}
    assert by == {"p000": "same | shadow [0, 0.05)", "p001": "same | shadow [0.05, 0.15)",
                  "p002": "same | shadow [0.15, 0.3)", "p003": "same | shadow [0.3, 1]"}
    with pytest.raises(UserError, match="has no light_category"):
        P.stratify(_rows("A", [0.1]), "light_category")
    with pytest.raises(UserError, match="strata=nope"):
        P.stratify(rows, "nope")


def test_extra_columns_round_trip_and_render(tmp_path):
    rows = _rows("A", [0.1, 0.2], extra={"identity_gt": 0.9, "shadow_adherence": math.nan},
                 info=lambda i: {"light_category": "sun", "shadow_share": "0.01"})
    path = T.write_records(tmp_path / T.PER_IMAGE_CSV, rows)
    back = T.read_records(path)
    assert back[0].extra["identity_gt"] == 0.9 and math.isnan(back[0].extra["shadow_adherence"])
    assert back[1].info == {"light_category": "sun", "shadow_share": "0.01"}
    table = T.summarize(back)
    assert table.metrics == ["dssim", "mse", "lpips", "identity_gt", "shadow_adherence"]
    md = table.to_markdown()
    assert "ID vs GT" in md and "**0.9000 ± 0.0000**" in md and "A cell's (n=k)" in md
    assert table.cells[("A", "same")]["shadow_adherence"].n == 0


def _table_cfg(out, runs, *extra):
    from tests.helpers import compose_train

    return compose_train(out, [f"runs=[{','.join(str(r) for r in runs)}]", f"out={out}", *extra],
                         config_name="table")


def test_table_cli_paired_strata_and_published_values(tmp_path):
    from difareli.cli.table import run

    a = np.linspace(0.1, 0.3, 12)
    info = lambda i: {"light_category": ["sun", "dim"][i % 2]}  # noqa: E731
    for name, v in (("A", a), ("B", a + 0.01)):
        T.write_records(tmp_path / name / T.PER_IMAGE_CSV, _rows(name, v, info=info))
    run(_table_cfg(tmp_path / "out", [tmp_path / "A", tmp_path / "B"], "n_boot=500"))
    text = (tmp_path / "out" / "paired.md").read_text()
    assert "| (i) same subject | DSSIM | A | B | 12 | +0.01 | [+0.01, +0.01] |" in text
    csv_rows = (tmp_path / "out" / "paired.csv").read_text().splitlines()
    assert csv_rows[0].startswith("protocol,metric,a,b,n,mean_b_minus_a") and len(csv_rows) == 4  # 3 metrics
    run(_table_cfg(tmp_path / "s", [tmp_path / "A", tmp_path / "B"], "strata=light_category", "n_boot=500"))
    # the stratum stays in the protocol's cell: a pipe there would shift every later column
    assert "| (i) same subject, light_category=dim | DSSIM | A | B | 6 |" in (tmp_path / "s" / "paired.md").read_text()
    T.write_records(tmp_path / "C" / T.PER_IMAGE_CSV, _rows("C", a[:10]))
    with pytest.raises(UserError, match="A and C were scored on different same pairs"):
        run(_table_cfg(tmp_path / "x", [tmp_path / "A", tmp_path / "C"], "paired=strict"))
    for bad in ("published=0", "published=1"):
        with pytest.raises(UserError, match="published= accepts null or false"):
            run(_table_cfg(tmp_path / "y", [tmp_path / "A"], bad))


def test_significance_sentence_names_orderings_from_the_numbers():
    a = np.random.default_rng(2).uniform(0.1, 0.3, 40)
    eps = np.repeat(np.random.default_rng(3).uniform(0.001, 0.02, 20), 2) * np.tile([1, -1], 20)
    assert eps.sum() == 0  # symmetric noise: every +e has its -e
    ident = {"identity_gt": 0.8}
    rows = (_rows("A", a, extra=ident) + _rows("B", a + 0.01, extra={"identity_gt": 0.9})
            + _rows("C", a + eps, extra=ident))
    comps, _ = P.compare(rows, ["dssim", "identity_gt"], n_boot=2000, seed=1)
    by = {(c.a, c.b, c.metric): c for c in comps}
    shift, noise = by[("A", "B", "dssim")], by[("A", "C", "dssim")]
    assert shift.lo > 0 and shift.p < 0.05  # better by a constant on every pair: the CI excludes 0
    assert noise.mean == pytest.approx(0, abs=1e-12) and noise.lo < 0 < noise.hi and noise.p > 0.9
    text = P.significance(comps)
    yes, no = text.split("; not significant: ")
    assert yes.startswith("At the 5% level (Wilcoxon p < 0.05 and the bootstrap 95% CI excluding 0; each of the 6 "
                          "comparisons on its own, no multiple-comparison correction), significant: "
                          "(i) same subject DSSIM: A better than B (p=")
    assert "C better than B" in yes and "A vs C" not in yes  # C = A + noise is 0.01 below B on every pair as well
    assert "(i) same subject ID vs GT: B better than A" in yes  # higher is better for identity
    assert f"(i) same subject DSSIM: A vs C (p={P._p(noise.p)})" in no and no.endswith(".")
    assert "(i) same subject ID vs GT: A vs C (p=n/a)" in no  # every difference 0: no test
    assert "significant: none" in P.significance([c for c in comps if c.b == "C" and c.a == "A"])
    # the tests disagree: 15 small gains and one large loss (Wilcoxon p < 0.05, the mean's CI covers 0)
    d = np.array([0.01] * 15 + [-1.0])
    (c,) = P.compare(_rows("X", np.ones(16)) + _rows("Y", 1 + d), ["dssim"], n_boot=2000)[0]
    assert c.p < 0.05 and c.lo < 0 < c.hi
    assert P.significance([c]).endswith("not significant: (i) same subject DSSIM: X vs Y (p=" + P._p(c.p)
                                        + ") (the CI and p disagree).")


def _scored_on(run_dir, identity, store):
    """Record in ``run_dir`` the store it was scored on, as difareli-benchmark does (settings and provenance)."""
    import json

    (run_dir / "benchmark_settings.json").write_text(json.dumps({"store": identity}))
    (run_dir / "provenance.json").write_text(json.dumps({"store": f"{store} ({identity})"}))


def test_runs_on_stores_of_different_identities_are_not_paired(tmp_path):
    """The same record ids in another store are other images: strict refuses naming both runs and stores, auto
    compares nothing across them and says why; runs of one store still pair."""
    from difareli.cli.table import run

    a = np.linspace(0.1, 0.3, 12)
    for name, v in (("A", a), ("B", a + 0.01), ("C", a + 0.02)):
        T.write_records(tmp_path / name / T.PER_IMAGE_CSV, _rows(name, v))
    _scored_on(tmp_path / "A", "sha256:aaaa", "/data/storeA")
    _scored_on(tmp_path / "B", "sha256:bbbb", "/data/storeB")
    _scored_on(tmp_path / "C", "sha256:aaaa", "/data/storeA")
    runs = [tmp_path / "A", tmp_path / "B"]
    with pytest.raises(UserError) as e:
        run(_table_cfg(tmp_path / "x", runs, "paired=strict", "n_boot=200"))
    assert str(e.value) == (f"paired comparison: A (run dir {tmp_path / 'A'}) was scored on store /data/storeA "
                            f"(sha256:aaaa) and B (run dir {tmp_path / 'B'}) on store /data/storeB (sha256:bbbb), so "
                            "their rows of one record id are not the same pair; compare runs benchmarked on one "
                            "store, or pass paired=auto to skip such pairs of methods")
    assert not (tmp_path / "x" / "paired.md").exists()
    run(_table_cfg(tmp_path / "y", [*runs, tmp_path / "C"], "n_boot=200"))
    text = (tmp_path / "y" / "paired.md").read_text()
    assert "| DSSIM | A | C | 12 | +0.02 |" in text and "DSSIM | A | B |" not in text and "DSSIM | B | C |" not in text
    assert text.count("not compared: A (run dir") == 1 and "not compared: B (run dir" in text
