"""difareli-benchmark's score_mask: the mask key pairs are scored on (face_mask by default, or a v3
store's exact face_mask_gt); refused when the store lacks it, recorded in the settings a resume must match and
stated in the summary."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from difareli import errors
from difareli.evaluation.baselines import Identity
from difareli.evaluation.benchmark import SETTINGS, run_benchmark
from difareli.evaluation.scoring import Scoring
from difareli.errors import UserError
from difareli.data.store import EncodingStore

from tests.helpers import compose_train

pytestmark = pytest.mark.usefixtures("one_thread")
SAME = ["same_subject"]


def _with_gt_mask(src, dst, change=None):
    """A copy of ``src`` with a ``face_mask_gt`` encoding: the record's face_mask, or ``change(face_mask)``."""
    shutil.copytree(src, dst)
    header = json.loads((dst / "store.json").read_text())
    header["encodings"].append("face_mask_gt")
    (dst / "store.json").write_text(json.dumps(header, indent=2, sort_keys=True) + "\n")
    for rec in (dst / "records").iterdir():
        m = np.load(rec / "face_mask.npy")
        np.save(rec / "face_mask_gt.npy", m if change is None else change(m))
    return EncodingStore.open(dst)


def _scores(res):
    return sorted((r.protocol, r.record_id, r.dssim, r.mse, r.lpips) for r in res.records)


def test_face_mask_gt_equal_to_face_mask_scores_the_same_and_another_mask_differs(synth_store, tmp_path):
    same = _with_gt_mask(synth_store, tmp_path / "same")
    kw = {"limit": 2, "progress": False, "grid_pairs": 0, "save_images": False}
    base = run_benchmark(same, Identity(), SAME, tmp_path / "a", **kw)
    gt = run_benchmark(same, Identity(), SAME, tmp_path / "b", scoring=Scoring.of(same, score_mask="face_mask_gt"),
                       **kw)
    assert _scores(gt) == _scores(base) and all(r.mse > 1e-4 for r in base.records)

    def top_half_off(m):
        m = m.copy()
        m[: m.shape[0] // 2] = False
        return m

    other = _with_gt_mask(synth_store, tmp_path / "other", top_half_off)
    half = run_benchmark(other, Identity(), SAME, tmp_path / "c", scoring=Scoring.of(other, score_mask="face_mask_gt"),
                         **kw)
    assert len(half.records) == len(base.records) == 2
    for a, b in zip(sorted(half.records, key=lambda r: r.record_id), sorted(base.records, key=lambda r: r.record_id)):
        assert a.record_id == b.record_id and a.mse != pytest.approx(b.mse, rel=1e-6)
        assert a.dssim != pytest.approx(b.dssim, rel=1e-6)
    # Recorded and stated: the settings a resume must match, the summary's inputs line and provenance.json.
    assert json.loads((tmp_path / "c" / SETTINGS).read_text())["score_mask"] == "face_mask_gt"
    assert "score mask: face_mask_gt" in (tmp_path / "c" / "summary.md").read_text().splitlines()[0]
    assert json.loads((tmp_path / "c" / "provenance.json").read_text())["score mask"] == "face_mask_gt"
    assert "score mask: face_mask;" in (tmp_path / "a" / "summary.md").read_text().splitlines()[0] + ";"
    rows = (tmp_path / "c" / "metrics_per_image.csv").read_bytes()
    with pytest.raises(UserError, match=r"holds benchmark rows made with other settings \(score_mask: "
                                        r"'face_mask_gt' there, 'face_mask' now\)"):
        run_benchmark(other, Identity(), SAME, tmp_path / "c", **kw)
    assert (tmp_path / "c" / "metrics_per_image.csv").read_bytes() == rows  # the refused run changed nothing


def test_a_mask_the_store_lacks_is_refused_naming_its_masks(synth_store, tmp_path, monkeypatch, capsys):
    from difareli.cli.benchmark import run

    monkeypatch.delenv("DIFARELI_DEBUG", raising=False)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    for key, what in (("face_mask_gt", "has no face_mask_gt"),
                      ("image", "has image but it is not a mask (a bool HxW encoding)")):
        cfg = compose_train(tmp_path / key, [f"store={synth_store}", "progress=false", "num_threads=null",
                                             "method=identity", f"score_mask={key}"], config_name="benchmark")
        with pytest.raises(SystemExit) as e:
            errors.cli_entry("benchmark")(lambda cfg=cfg: run(cfg))()
        assert e.value.code == 2
        assert capsys.readouterr().err == (
            f"difareli-benchmark: score_mask={key}: store {synth_store} {what}; give one "
            "of its masks: face_mask, shadow_visible_gt (default score_mask=face_mask)\n")
        assert not (tmp_path / key / SETTINGS).exists() and not (tmp_path / key / "metrics_per_image.csv").exists()


def test_a_run_recorded_before_the_option_resumes_on_face_mask(synth_store, tmp_path):
    """benchmark_settings.json written before score_mask existed (no key): the default mask resumes into it."""
    store = _with_gt_mask(synth_store, tmp_path / "gt")
    kw = {"limit": 2, "progress": False, "grid_pairs": 0, "save_images": False}
    run_benchmark(store, Identity(), SAME, tmp_path / "old", **kw)
    path = tmp_path / "old" / SETTINGS
    settings = json.loads(path.read_text())
    del settings["score_mask"]
    path.write_text(json.dumps(settings))
    assert len(run_benchmark(store, Identity(), SAME, tmp_path / "old", **kw).records) == 2
    with pytest.raises(UserError, match=r"score_mask: None there, 'face_mask_gt' now"):
        run_benchmark(store, Identity(), SAME, tmp_path / "old", scoring=Scoring.of(store, score_mask="face_mask_gt"),
                      **kw)
