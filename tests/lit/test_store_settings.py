"""An existing store whose settings differ from data.synth is refused naming them, never silently reused."""

from __future__ import annotations

import pytest

from difareli.cli.train import train
from difareli.errors import UserError
from difareli.lit.datamodule import EncodingsDataModule
from tests.helpers import compose_train, tiny_cpu_overrides

# What conftest's synth_store was generated with (generate()'s defaults for the rest).
MADE = {"subjects": 8, "lights": 2, "seed": 0}


def _dm(store, synth, resolution=32):
    return EncodingsDataModule(root=str(store), spatial=["shading"], resolution=resolution, synth=synth)


def test_the_same_settings_reuse_the_store(synth_store):
    dm = _dm(synth_store, dict(MADE))
    dm.prepare_data()  # no error: nothing regenerated, nothing refused
    assert dm.input_dims()  # and it opens


def test_other_settings_are_refused_naming_each_and_the_fix(synth_store):
    with pytest.raises(UserError) as e:
        _dm(synth_store, {**MADE, "subjects": 16, "seed": 3}).prepare_data()
    msg = str(e.value)
    assert "subjects: 8 in the store, 16 asked" in msg and "seed: 0 in the store, 3 asked" in msg
    assert "lights" not in msg  # only what differs
    assert "use another data.root" in msg and "data.synth=null" in msg and str(synth_store) in msg


def test_a_realism_default_that_differs_is_named_too(synth_store):
    # The store was rendered lambertian (generate()'s default); asking for full realism would render other images.
    with pytest.raises(UserError, match=r"realism: 'lambertian' in the store, 'full' asked"):
        _dm(synth_store, {**MADE, "realism": "full"}).prepare_data()


def test_synth_null_uses_the_store_as_it_is(synth_store):
    _dm(synth_store, None).prepare_data()


def test_difareli_train_refuses_before_training(synth_store, tmp_path):
    over = [o for o in tiny_cpu_overrides(synth_store) if o != "data.synth=null"]
    # The case: data.synth.subjects=16 on a root that already holds an 8-subject store.
    cfg = compose_train(tmp_path, [*over, "model=difareli", "data.synth.subjects=16", "data.synth.lights=2",
                                   "data.synth.seed=0", "trainer.max_steps=1"])
    with pytest.raises(UserError, match=r"subjects: 8 in the store, 16 asked"):
        train(cfg)
    assert not (tmp_path / "checkpoints").exists()  # refused before any training
