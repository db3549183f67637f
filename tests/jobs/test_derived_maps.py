"""One shadow-map maker: difareli-shadow-maps maker=march writes each record's training map with the
very function a relight makes its target maps with, records that maker, and a relight of a model trained on
another maker's maps says so, naming both."""

from __future__ import annotations

import shutil
import warnings

import numpy as np
import pytest

from difareli.data import encodings
from difareli.data.inputs import read_record
from difareli.data.store import EncodingStore
from difareli.errors import UserError
from difareli.lighting.suns import Suns
from difareli.jobs import derived_maps
from difareli.render.retarget import check_maker, shadow_maker, target_shadow_map


@pytest.fixture
def store(synth_store, tmp_path):
    shutil.copytree(synth_store, tmp_path / "store")
    return EncodingStore.open(tmp_path / "store", durable=False)


def test_march_maps_are_the_relights_own_target_maps(store):
    rep = derived_maps.compute(store, method="march", light="exact", progress=False)
    assert rep.written == rep.records == len(store.ids()) and rep.provenance["maker"] == shadow_maker()
    lit = 0
    for rid in store.ids():
        a = read_record(store, rid, ["depth", "normal", "cam", "light_gt", "shadow_gt"])
        suns = Suns.from_header(store.meta(rid), a["light_gt"])  # SynthFaces: the header's suns, not the SH
        assert suns is not None or not np.any(store.meta(rid).get("sun_rgb", 0))
        want = target_shadow_map(a, suns if suns is not None else a["light_gt"], encodings.shadow_logit(a, "shadow_gt"))
        got = store.read(rid, [rep.name])[rep.name]
        np.testing.assert_array_equal(got, want)  # bit for bit: the same maker, the same light and c
        lit += int((got > 0).any())
    assert lit > 0, "no record has a marched shadow: the test would not see a wrong maker"
    fitted = derived_maps.compute(store, method="march", light="fitted", progress=False)
    assert fitted.name != rep.name and EncodingStore.open(store.root).derived[fitted.name]["light"] == "fitted"
    again = derived_maps.compute(store, method="march", light="exact", progress=False)
    assert again.name == rep.name and again.written == 0  # resumed: nothing to do


def test_visible_maps_are_the_exact_visible_shadows_times_c(store):
    if not store.available("shadow_visible_gt"):
        with pytest.raises(UserError, match="shadow_visible_gt"):
            derived_maps.compute(store, method="visible", progress=False)
        return
    rep = derived_maps.compute(store, method="visible", progress=False)
    rng = encodings.store_c_range(store.store_meta)
    for rid in store.ids()[:4]:
        a = store.read(rid, ["shadow_visible_gt", "shadow_gt", rep.name])
        c = encodings.shadow_logit(a, "shadow_gt")
        np.testing.assert_array_equal(a[rep.name],
                                      (a["shadow_visible_gt"] * encodings.normalise_c(c, rng)).astype(np.float32))


def test_a_store_without_what_a_maker_reads_is_refused_by_name(store):
    with pytest.raises(UserError, match=r"maker='mesh' is not a map maker here"):
        derived_maps.compute(store, method="mesh", progress=False)
    with pytest.raises(UserError, match=r"light='sun'"):
        derived_maps.compute(store, method="march", light="sun", progress=False)


def test_check_maker_is_silent_for_the_same_maker_and_names_both_otherwise():
    now = shadow_maker()
    assert check_maker(now) is None and check_maker(None) is None
    assert check_maker({"name": "visible", "version": "visible"}) is None  # the exact shadows: no other maker
    msg = check_maker({"name": "mesh", "light": "fitted"})
    assert "made by mesh (light=fitted)" in msg and "made by march (" in msg
    older = {**now, "thickness": now["thickness"] * 2}
    assert "differ in thickness" in check_maker(older)


def test_the_datamodule_names_the_maker_of_the_maps_it_reads(store):
    from difareli.lit.datamodule import EncodingsDataModule

    rep = derived_maps.compute(store, method="march", progress=False)
    version = rep.name.split("@", 1)[1]
    dm = EncodingsDataModule(root=str(store.root), spatial=["shading", "shadow_map"], nonspatial=[],
                             versions={"shadow_map": version}, synth=None, resolution=32)
    assert dm.shadow_map_maker() == shadow_maker()
    plain = EncodingsDataModule(root=str(store.root), spatial=["shading", "shadow_map"], nonspatial=[],
                                synth=None, resolution=32)
    assert plain.shadow_map_maker()["name"] == "mesh"
    # A student's pairs: the target maps are re-rendered by the relight's maker, whatever the store holds; only
    # ground-truth pairs that read the target record's stored map name the store's (here its mesh rays).
    for pairs, gt_maps in (("gt", "march"), ("teacher", "march"), ("mix", "stored"), ("identity", "march")):
        student = EncodingsDataModule(root=str(store.root), spatial=["shading", "shadow_map"], nonspatial=[],
                                      synth=None, resolution=32, pairs=pairs, gt_maps=gt_maps)
        assert student.shadow_map_maker() == shadow_maker(), (pairs, gt_maps)
    stored = EncodingsDataModule(root=str(store.root), spatial=["shading", "shadow_map"], nonspatial=[],
                                 synth=None, resolution=32, pairs="gt", gt_maps="stored")
    assert stored.shadow_map_maker()["name"] == "mesh"


def test_a_relighter_warns_once_when_its_model_trained_on_another_makers_maps(tiny_checkpoint):
    import torch

    from difareli.relight.relighter import Relighter

    path = tiny_checkpoint("difareli_pp")
    ckpt = torch.load(path, weights_only=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        Relighter(path)
    trained = ckpt["hyper_parameters"].get("training_maps")
    mine = [w for w in caught if "trained on shadow maps made by" in str(w.message)]
    assert trained and trained["name"] == "mesh" and len(mine) == 1  # SynthFaces' mesh maps, not the march
