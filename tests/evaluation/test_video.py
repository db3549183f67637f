"""Moving-light videos (difareli.evaluation.video, difareli-video): IoU on known shapes, temporal change closed forms,
the shadow rule against exact SynthFaces cast maps, the typical-c policy and the CLI's frame count and outputs."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.data import target_shadow
from difareli.relight import request
from difareli.evaluation import video as vid
from difareli.data.store import EncodingStore
from difareli.errors import UserError

from tests.helpers import compose_train

pytestmark = pytest.mark.usefixtures("one_thread")


def test_iou_of_known_shapes():
    a = np.zeros((3, 8, 8), bool)
    b = np.zeros((3, 8, 8), bool)
    a[0, :4, :4] = True          # 16 px
    b[0, 2:6, :4] = True         # 16 px, 8 shared -> 8 / 24
    a[1, :2] = b[1, :2] = True   # identical -> 1
    out = vid.iou(a, b)          # frame 2: both empty -> NaN
    np.testing.assert_allclose(out[:2], [1 / 3, 1.0])
    assert math.isnan(out[2])


def test_frame_changes_and_temporal_error_closed_form():
    frames = np.zeros((3, 4, 4, 3), np.uint8)
    frames[1] = 51    # 0.2
    frames[2] = 153   # 0.6
    mask = np.zeros((4, 4), bool)
    mask[1:3, 1:3] = True
    np.testing.assert_allclose(vid.frame_changes(frames, mask), [0.2, 0.4])
    still = np.repeat(frames[:1], 3, axis=0)
    np.testing.assert_allclose(vid.temporal_error(still, frames, mask), [0.2, 0.4])
    np.testing.assert_allclose(vid.temporal_error(frames, frames, mask), [0.0, 0.0])


def test_typical_shadowed_c_ignores_unshadowed_records():
    no = math.log(1e-3 / (1 - 1e-3))
    assert target_shadow.typical_shadowed_c(np.array([no, no, -3.0, -2.0, -1.0])) == pytest.approx(-2.0)
    assert target_shadow.typical_shadowed_c(np.array([no, no])) is None


@pytest.fixture(scope="module")
def rotation(synth_store):
    from difareli.synth import rotation as rot

    store = EncodingStore.open(synth_store)
    # The record with the strongest cast shadow under its own light.
    rid = max(store.ids(), key=lambda r: float(store.read(r, ["shadow_gt"])["shadow_gt"][0]))
    return store, rid, rot.ground_truth_rotation(store, rid, "yaw", frames=8)


def rule_lights(store, rid, gt):
    """The exact suns of each frame and of the input, as difareli-video gives the rule."""
    from difareli.synth import rotation as rot

    return gt.suns(), rot.source_suns(store, rid)


def test_measure_ground_truth_against_itself(rotation):
    store, rid, gt = rotation
    arrays = store.read(rid)
    frames, source = rule_lights(store, rid, gt)
    rep = vid.measure(gt.frames, gt.frames, arrays, frames, gt.cast(), input_light=source)
    np.testing.assert_allclose(rep.per_frame["mse"], 0.0, atol=1e-12)
    np.testing.assert_allclose(rep.per_frame["dssim"], 0.0, atol=1e-9)
    # The ground truth relit as itself scores what the rule scores on it, frame by frame.
    np.testing.assert_array_equal(rep.per_frame["shadow_iou"], rep.per_frame["rule_iou"])
    np.testing.assert_allclose(rep.changes["error"], 0.0)
    np.testing.assert_allclose(rep.changes["relit"], rep.changes["gt"])


def test_frames_without_cast_shadows_score_near_zero(rotation):
    # The floor of the shadow IoU: the subject rendered under each frame's light with no cast shadow (a relight
    # perfect but for the shadow) against the ground truth's exact shadows.
    store, rid, gt = rotation
    flat = gt.without_shadows()
    assert not flat.cast().any() and gt.cast().any()
    np.testing.assert_array_equal(flat.targets["light"], gt.targets["light"])  # same lights, shadows gone
    frames, source = rule_lights(store, rid, gt)
    rep = vid.measure(flat.frames, gt.frames, store.read(rid), frames, gt.cast(), input_light=source,
                      shadowless=flat.frames)
    assert np.nanmean(rep.per_frame["shadow_iou"]) < 0.05 < np.nanmean(rep.per_frame["rule_iou"])
    # the floor, by name
    np.testing.assert_array_equal(rep.per_frame["floor_iou"], rep.per_frame["shadow_iou"])


def test_shadow_rule_finds_exact_cast_shadows(rotation):
    # The rule (which reads no GT) against the exact cast maps of a sunny SynthFaces rotation.
    store, rid, gt = rotation
    arrays = store.read(rid)
    frames, source = rule_lights(store, rid, gt)
    found, judged = vid.detect_cast_shadow(gt.frames, arrays, frames, source)
    truth = gt.cast() & judged
    assert truth.sum() > 0, "the strongest-shadow record casts shadows somewhere in its rotation"
    inter, union = (found & truth).sum(), (found | truth).sum()
    # Without the realism effects (specular, subsurface, AO) the exact suns predict the unshadowed image exactly:
    # only the 8-bit rounding and the visible-share cut separate the rule from the truth (0.987 measured; the
    # smooth SH prediction the rule used before found 0.909 of a smaller judged region).
    assert inter / union > 0.95, f"pooled IoU of the rule vs exact cast maps: {inter / union:.3f}"


def test_target_shadow_policy(synth_store):
    store = EncodingStore.open(synth_store)
    c, note = request.video_shadow(store, -6.9, None)
    want = target_shadow.typical_shadowed_c(np.array([store.read(r, ["shadow"])["shadow"][0]
                                                for r in store.ids(split="train")]))
    assert c == pytest.approx(want) and "median c of the train split" in note
    assert request.video_shadow(store, -2.0, None)[0] == -2.0
    assert request.video_shadow(store, -6.9, -1.5) == (-1.5, "target c' = -1.500 (given: target.shadow)")


def test_video_cli_frames_and_outputs(tiny_checkpoint, synth_store, tmp_path):
    from difareli.cli.video import run

    cfg = compose_train(tmp_path, [f"checkpoint={tiny_checkpoint('difareli_pp')}", f"store={synth_store}",
                                   "rotation.frames=4", "sampler.steps=3", "progress=false", "runtime.device=cpu",
                                   "sheet_columns=4"], config_name="video")
    written = run(cfg)
    relit, gt = iio.imread(written["relit"]), iio.imread(written["gt"])
    assert relit.shape == (4, 32, 32, 3) and gt.shape == (4, 32, 32, 3)
    store = EncodingStore.open(synth_store)
    rid = store.ids(split="test")[0]
    # Frame 0 is the record itself, up to the GIF's 256-colour palette (write_gif's fast octree, no dithering: a
    # mean of ~1.6 levels here, ~3 on 512 px photos); an MP4 is lossy in another way, so only a GIF is held to it.
    diff = np.abs(gt[0].astype(int) - store.read(rid, ["image"])["image"])
    if written["gt"].suffix == ".gif":
        assert diff.mean() < 2.5 and diff.max() <= 16, (diff.mean(), diff.max())
    assert iio.imread(written["sheet"]).shape == (2 * 34 + 2, 4 * 34 + 2, 3)  # GT row over the relit row
    rows = list(csv.DictReader(open(written["csv"])))
    assert [float(r["angle"]) for r in rows] == [0.0, 90.0, 180.0, 270.0]
    summary = json.loads(Path(written["summary"]).read_text())
    assert summary["frames"] == 4 and "target c'" in summary["shadow"] and not summary["oracle_shadow"]
    assert 0 <= summary["dssim_mean"] <= 1 and summary["change_gt_mean"] > 0
    assert 0 <= summary["floor_iou_mean"] <= summary["rule_iou_mean"] <= 1  # the floor, and the rule on the truth
    assert summary["target_sun"] == "shadows" and summary["target_maps"].startswith("target shadow maps marched toward")


def test_video_cli_checks_its_store_record_and_sampler_before_the_checkpoint(synth_store, tmp_path):
    from difareli.cli.video import run

    ckpt = tmp_path / "c.ckpt"
    ckpt.write_bytes(b"x")  # read, it would be refused as "not a readable PyTorch file": the store is said first
    for override, want in {"record=s9_l9": r"^record=s9_l9: no such record in the store .*; give one of its record ids",
                           f"store={tmp_path}/none": "no encoding store at",
                           "versions.shadow_map=v9": "versions.shadow_map='v9'",
                           "sampler.name=euler": "sampler.name='euler' is not a sampler",
                           "+sampler.foo=1": "unknown option 'foo' for sampler",
                           "runtime.precision=fp8": "runtime.precision='fp8' is not one of",
                           "batch_size=0": "batch_size=0 is invalid"}.items():
        store = [] if override.startswith("store=") else [f"store={synth_store}"]
        cfg = compose_train(tmp_path / "run", [f"checkpoint={ckpt}", *store, override], config_name="video")
        with pytest.raises(UserError, match=want):
            run(cfg)
