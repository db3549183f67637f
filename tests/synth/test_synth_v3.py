"""SynthFaces v3: the visibly-shadowed ground truth, the store's own c range, v2 stores kept apart,
and (slow, needs the photo estimators) every input estimated from the rendered image."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from difareli.data import encodings
from difareli.data.store import EncodingStore
from difareli.synth import generator as gen
from difareli.synth import config as synth_config
from difareli.synth.c_norm import finalise
from difareli.synth.estimated import mode_downsample

from tests.helpers import HAS_FACE_RECOGNITION, NO_ESTIMATORS


def test_every_store_records_the_visible_shadow(synth_store):
    s = EncodingStore.open(synth_store)
    assert s.store_meta["synthfaces_version"] == 3 and s.store_meta["shadow_visible"] == 0.25
    for rid in s.ids()[:6]:
        a = s.read(rid, ["shadow_fraction_gt", "shadow_visible_gt", "shadow_map_gt", "depth"])
        frac, vis = np.asarray(a["shadow_fraction_gt"]), np.asarray(a["shadow_visible_gt"])
        assert ((frac > 0.25) <= vis).all() and (vis <= (np.asarray(a["depth"]) != 0)).all()
        assert ((np.asarray(a["shadow_map_gt"]) > 0) <= (frac > 0)).all()  # every cast pixel loses some light


def test_the_unshadowed_image_is_the_same_light_with_no_cast_shadow(synth_store):
    """``image_unshadowed_gt``: the record rendered again with every sun reaching every point: equal to the image
    where no cast shadow falls and brighter inside the visible shadows."""
    s = EncodingStore.open(synth_store)
    brighter = 0
    for rid in s.ids()[:8]:
        a = s.read(rid, ["image", "image_unshadowed_gt", "shadow_fraction_gt", "shadow_visible_gt"])
        img, free = np.asarray(a["image"], float), np.asarray(a["image_unshadowed_gt"], float)
        frac, vis = np.asarray(a["shadow_fraction_gt"]), np.asarray(a["shadow_visible_gt"])
        np.testing.assert_array_equal(img[frac == 0], free[frac == 0])
        assert (free >= img).all()  # a cast shadow only takes light away
        if vis.sum() > 4:
            assert (free - img).mean(-1)[vis].mean() > 5  # grey levels, inside the visible shadows
            brighter += 1
    assert brighter >= 1


def test_normalise_c_ranges_and_target_maps_use_the_records_range():
    np.testing.assert_allclose(encodings.normalise_c([-5.0, -3.0, 0.0], (-4.0, -2.0)), [0.0, 0.5, 1.0])
    np.testing.assert_allclose(encodings.normalise_c(encodings.SHADOW_C_HI), 1.0)  # the fixed range
    with pytest.raises(ValueError, match="empty"):
        encodings.normalise_c(0.0, (1.0, 1.0))
    assert encodings.store_c_range({}) is None
    assert encodings.store_c_range({encodings.C_RANGE_KEY: {"lo": -4, "hi": -2}}) == (-4.0, -2.0)
    assert encodings.store_c_range({encodings.C_RANGE_KEY: np.array([-4.0, -2.0])}) == (-4.0, -2.0)


def test_finalise_scales_maps_by_the_train_split_range(synth_store, tmp_path):
    from difareli.render.retarget import target_shadow_map

    shutil.copytree(synth_store, tmp_path / "s")
    store = EncodingStore.open(tmp_path / "s", writable=True, durable=False)
    before = {r: store.read(r, ["shadow", "shadow_gt", "shadow_map", "shadow_visible_gt"]) for r in store.ids()}
    before = {r: {k: np.array(v) for k, v in a.items()} for r, a in before.items()}
    rng = finalise(store, 0.0)
    train = [float(before[r]["shadow"][0]) for r in store.ids(split="train")]
    assert (rng["lo"], rng["hi"]) == pytest.approx((min(train), max(train)), abs=1e-6)  # the authors' min / max
    assert rng["state"] == "final" and json.loads((tmp_path / "s" / "store.json").read_text())["meta"][
        encodings.C_RANGE_KEY]["state"] == "final"
    c_range = (rng["lo"], rng["hi"])
    for r, a in before.items():
        got = store.read(r, ["shadow_map", "shadow_map_gt"])
        np.testing.assert_allclose(got["shadow_map"], (a["shadow_map"] > 0) * encodings.normalise_c(
            a["shadow"][0], c_range), atol=1e-6)
        np.testing.assert_allclose(got["shadow_map_gt"], a["shadow_visible_gt"] * encodings.normalise_c(
            a["shadow_gt"][0], c_range), atol=1e-6)
    # Killed while scaling: a rerun gives the same maps (idempotent).
    first = {r: np.array(store.read(r, ["shadow_map"])["shadow_map"]) for r in store.ids()}
    store.store_meta[encodings.C_RANGE_KEY] = {**rng, "state": "scaling"}
    finalise(store, 0.0)
    for r in store.ids():
        np.testing.assert_array_equal(store.read(r, ["shadow_map"])["shadow_map"], first[r])
    # Target maps of this store's records use its range: the readers (inputs.read_record, behind Relighter.source,
    # the student's pairs and the training relight metrics) give it with the record.
    from difareli.data.inputs import read_record

    rid = store.ids()[0]
    a = read_record(store, rid, ["depth", "normal", "cam"])
    np.testing.assert_array_equal(a[encodings.C_RANGE_KEY], c_range)
    light = np.asarray(store.read(rid, ["light"])["light"])
    mid = (c_range[0] + c_range[1]) / 2
    fixed = target_shadow_map({k: a[k] for k in ("depth", "normal", "cam")}, light, mid)
    mine = target_shadow_map(a, light, mid)
    np.testing.assert_array_equal(mine > 0, fixed > 0)
    if (mine > 0).any():
        np.testing.assert_allclose(mine[mine > 0], 0.5, atol=1e-6)


def test_v2_stores_open_and_refuse_a_v3_resume(synth_store, tmp_path):
    shutil.copytree(synth_store, tmp_path / "v2")
    header_path = tmp_path / "v2" / "store.json"
    header = json.loads(header_path.read_text())
    header["meta"].pop("synthfaces_version")
    header_path.write_text(json.dumps(header))
    assert len(EncodingStore.open(tmp_path / "v2").ids()) == 16  # reads as before
    with pytest.raises(synth_config.ConfigError,
                       match=r"SynthFaces v2 store.*difareli-synth out_dir=<new dir> subjects=8"):
        gen.generate(str(tmp_path / "v2"), 8, 2, 32, seed=0)


def test_config_checks_and_the_resolved_estimation_resolution():
    cfg = synth_config.SynthConfig(subjects=1, lights=1, resolution=64, inputs="estimated")
    assert cfg.estimation_resolution == 128 and "normal_gt" in cfg.encodings
    assert synth_config.SynthConfig(subjects=1, lights=1, resolution=256).estimation_resolution == 256
    assert "normal_gt" not in synth_config.SynthConfig(subjects=1, lights=1, resolution=64,
                                                       inputs="estimated_light").encodings
    for bad in ({"estimation_resolution": 96}, {"inputs": "guessed"}, {"shadow_visible": 1.5}):
        with pytest.raises(synth_config.ConfigError):
            synth_config.SynthConfig(subjects=1, lights=1, resolution=64, **bad)


def test_mode_downsample_keeps_the_majority_label():
    big = np.zeros((8, 8), np.uint8)
    big[:4, :4] = 3
    big[0, 0] = 5  # a minority pixel in the block
    small = mode_downsample(big, 2)
    np.testing.assert_array_equal(small, [[3, 0], [0, 0]])
    assert mode_downsample(big, 8) is big


@pytest.mark.slow
@pytest.mark.skipif(not HAS_FACE_RECOGNITION, reason=NO_ESTIMATORS)
def test_v3_store_estimates_every_input(tmp_path):
    rep = gen.generate(str(tmp_path / "v3"), 2, 2, 64, seed=0, realism="full", inputs="estimated")
    store = EncodingStore.open(tmp_path / "v3")
    assert rep.written == 4 and store.store_meta[encodings.C_RANGE_KEY]["state"] == "final"
    for rid in store.ids():
        a = store.read(rid)
        assert "inputs_fallback" not in store.meta(rid)
        for name in ("normal", "masks", "shape", "cam", "identity"):
            assert not np.array_equal(a[name], a[f"{name}_gt"]), name  # estimated, not the renderer's
        n, g = np.asarray(a["normal"]), np.asarray(a["normal_gt"])
        both = (np.linalg.norm(n, axis=-1) > 0.5) & (np.linalg.norm(g, axis=-1) > 0.5)
        assert both.sum() > 300 and np.degrees(np.arccos(np.clip((n * g)[both].sum(-1), -1, 1))).mean() < 25
        fm, fg = np.asarray(a["face_mask"]), np.asarray(a["face_mask_gt"])
        assert (fm & fg).sum() / (fm | fg).sum() > 0.5


def test_missing_estimators_stop_before_any_work(tmp_path, monkeypatch):
    import difareli.synth.estimated as est

    monkeypatch.setattr(gen, "missing_estimators", lambda: "inputs=estimated needs the photo estimators; " + est.FIX)
    with pytest.raises(synth_config.ConfigError, match="DIFARELI_PREPROCESS=1 bash scripts/install.sh"):
        gen.generate(str(tmp_path / "s"), 1, 1, 32, inputs="estimated")
    assert not (tmp_path / "s").exists()
