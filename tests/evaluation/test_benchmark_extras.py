"""The benchmark's extra columns (identity, lighting error, shadow adherence, strata) on known cases, and rescore's
refusals (another store, duplicated or missing rows)."""

import json
import math
import shutil

import numpy as np
import pytest

from difareli.errors import UserError
from difareli.evaluation import identity, tables

from tests.evaluation.test_benchmark import _bench_cfg


@pytest.fixture(scope="module")
def runs(synth_store, tmp_path_factory):
    from difareli.cli.benchmark import run

    root = tmp_path_factory.mktemp("extras")
    return root, {m: run(_bench_cfg(root / m, synth_store, f"method={m}", "grid_pairs=0", "limit=3"))
                  for m in ("identity", "oracle")}


def test_known_values_of_the_extra_columns(runs):
    root, res = runs
    header = (root / "oracle" / tables.PER_IMAGE_CSV).read_text().splitlines()[0].split(",")
    want = ["light_angle", "light_rel_error", "light_angle_gt", "shadow_adherence", "shadow_darkening", "shadow_iou",
            "light_category", "shadow_share"]
    if identity.unavailable() is None:
        want = ["identity_input", "identity_gt", *want]
    assert header == [*tables.COLUMNS, "rule", *want]
    for r in res["oracle"].records:  # the relit image is the ground truth itself
        assert r.extra["light_angle_gt"] == pytest.approx(0.0, abs=1e-6)
        if not math.isnan(r.extra["shadow_adherence"]):
            assert r.extra["shadow_adherence"] == 1.0
        if "identity_gt" in r.extra:
            assert r.extra["identity_gt"] == pytest.approx(1.0, abs=1e-6)
        assert r.info["light_category"] and 0 <= float(r.info["shadow_share"]) <= 1
    for r in res["identity"].records:  # the relit image is the input itself
        if "identity_input" in r.extra:
            assert r.extra["identity_input"] == pytest.approx(1.0, abs=1e-6)
        assert 0 <= r.extra["light_angle"] <= 180 and r.extra["light_rel_error"] >= 0
    # The input under another light: its fitted light is not the truth's (a metric that cannot tell them apart fails)
    assert np.nanmean([r.extra["light_angle_gt"] for r in res["identity"].records]) > 5.0
    summary = (root / "oracle" / "summary.md").read_text()
    assert "light angle (deg)" in summary and "target shadow M: shadow_" in summary


def test_rescore_refuses_another_store_and_bad_rows(runs, synth_store, tmp_path):
    from difareli.cli.benchmark import run

    root, _ = runs
    other = tmp_path / "other"
    shutil.copytree(synth_store, other)  # the same record ids, another store (another seed in its header)
    doc = json.loads((other / "store.json").read_text())
    doc["meta"]["seed"] = int(doc["meta"].get("seed", 0)) + 1
    (other / "store.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match=r"the run was scored on store .* is another one \(sha256:"):
        run(_bench_cfg(tmp_path / "re1", other, "method=identity", f"rescore={root / 'identity'}"))
    dup = tmp_path / "dup"
    shutil.copytree(root / "identity", dup)
    lines = (dup / tables.PER_IMAGE_CSV).read_text().splitlines(keepends=True)
    (dup / tables.PER_IMAGE_CSV).write_text("".join(lines + lines[1:3]))
    with pytest.raises(UserError, match=r"repeats 2 pair\(s\)"):
        run(_bench_cfg(tmp_path / "re2", synth_store, "method=identity", f"rescore={dup}"))
    (dup / tables.PER_IMAGE_CSV).write_text("".join(lines[:-1]))
    with pytest.raises(UserError, match=r"lacks 1 of the run's pairs"):
        run(_bench_cfg(tmp_path / "re3", synth_store, "method=identity", f"rescore={dup}"))
    # the run's own store: the same rows again, extra columns included
    again = run(_bench_cfg(tmp_path / "re4", synth_store, "method=identity", f"rescore={root / 'identity'}"))
    first = tables.read_records(root / "identity" / tables.PER_IMAGE_CSV)
    assert [(r.record_id, r.dssim) for r in again.records] == [(r.record_id, r.dssim) for r in first]
    assert np.allclose([r.extra["light_angle"] for r in again.records], [r.extra["light_angle"] for r in first])


def test_rescore_refuses_a_row_of_another_method_or_rule_naming_its_line(runs, synth_store, tmp_path):
    """A per-image CSV whose row was edited to another method (or rule) is refused naming the line, instead of
    rescoring the run's image under that name (the table gained a row of a method that was never run)."""
    from difareli.cli.benchmark import run

    root, _ = runs
    for column, value in (("method", "identity"), ("rule", "composite")):
        bad = tmp_path / f"bad_{column}"
        shutil.copytree(root / "oracle", bad)
        lines = (bad / tables.PER_IMAGE_CSV).read_text().splitlines(keepends=True)
        head = lines[0].rstrip("\n").split(",")
        row = lines[3].rstrip("\n").split(",")
        was, row[head.index(column)] = row[head.index(column)], value
        lines[3] = ",".join(row) + "\n"
        (bad / tables.PER_IMAGE_CSV).write_text("".join(lines))
        with pytest.raises(UserError) as e:
            run(_bench_cfg(tmp_path / f"re_{column}", synth_store, "method=identity", f"rescore={bad}"))
        assert str(e.value) == (f"rescore={bad}: {tables.PER_IMAGE_CSV} line 4 ({row[1]} {row[2]}) has {column} "
                                f"{value!r}, the run recorded {was!r} (benchmark_settings.json); the CSV was edited: "
                                "restore it or rerun the benchmark")
        assert not (tmp_path / f"re_{column}" / tables.PER_IMAGE_CSV).exists()


def test_rescore_of_a_tampered_or_missing_run_is_one_line(runs, synth_store, tmp_path):
    """Issue 64, our probe (difareli-benchmark rescore=<a copy of a run, one file changed>): a relit PNG replaced by
    text or a grey PNG ended in a traceback, one of another size in "pred/target must be equal NCHW tensors" naming
    no file; a corrupt provenance.json in a JSONDecodeError traceback, one nested 100,000 deep in a RecursionError;
    a corrupt benchmark_settings.json and a run dir that does not exist in "the run records no store identity"."""
    import imageio.v3 as iio

    from difareli.cli.benchmark import run

    root, _ = runs
    fix = "restore the run's relit images or rerun the benchmark"

    def first_png(d):
        return sorted((d / "relit").glob("*/*.png"))[0]

    cases = {
        "text": (lambda d: first_png(d).write_text("not a png"), "is not a readable image ("),
        "grey": (lambda d: iio.imwrite(first_png(d), np.zeros((32, 32), np.uint8)),
                 f"is 32x32 uint8, the benchmark writes 32x32x3 uint8 (the store's size); {fix}"),
        "small": (lambda d: iio.imwrite(first_png(d), np.zeros((16, 16, 3), np.uint8)),
                  f"is 16x16x3 uint8, the benchmark writes 32x32x3 uint8 (the store's size); {fix}"),
        "prov": (lambda d: (d / "provenance.json").write_text("{oops"),
                 "provenance.json is not the JSON object the benchmark writes (JSONDecodeError): corrupt; restore it "
                 "or rerun the benchmark"),
        "prov_deep": (lambda d: (d / "provenance.json").write_text("[" * 100_000 + "]" * 100_000),
                      "provenance.json is not the JSON object the benchmark writes (RecursionError)"),
        "settings": (lambda d: (d / "benchmark_settings.json").write_text('{"method": '),
                     "benchmark_settings.json is not the JSON object the benchmark writes (JSONDecodeError)"),
    }
    for name, (tamper, want) in cases.items():
        bad = tmp_path / name
        shutil.copytree(root / "oracle", bad)
        tamper(bad)
        with pytest.raises(UserError) as e:
            run(_bench_cfg(tmp_path / f"re_{name}", synth_store, "method=oracle", f"rescore={bad}"))
        msg = str(e.value)
        assert msg.startswith(f"rescore={bad}: ") and want in msg and "\n" not in msg, (name, msg)
        assert not (tmp_path / f"re_{name}" / tables.PER_IMAGE_CSV).exists()
    with pytest.raises(UserError) as e:
        run(_bench_cfg(tmp_path / "re_none", synth_store, "method=oracle", f"rescore={tmp_path / 'nope'}"))
    assert str(e.value) == (f"rescore={tmp_path / 'nope'} does not exist; give the out_dir of a finished "
                            "difareli-benchmark run (save_images=true)")
    with pytest.raises(UserError) as e:
        run(_bench_cfg(tmp_path / "re_store", synth_store, "method=oracle", f"rescore={synth_store}"))
    assert str(e.value) == (f"rescore={synth_store} is an encodings store, not a benchmark run dir; give the out_dir "
                            "of a finished difareli-benchmark run (save_images=true)")
