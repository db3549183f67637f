"""data.exact_share: one run trains on both kinds of inputs, each record served with its exact inputs (*_gt) at that
probability, its estimated ones otherwise; a store that keeps no exact counterpart is refused."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from difareli.errors import UserError
from difareli.lit.datamodule import EncodingsDataModule


@pytest.fixture(scope="module")
def two_kind_store(synth_store, tmp_path_factory):
    """The session store, its exact shading marked (+1) so that the two kinds differ in every pixel."""
    root = tmp_path_factory.mktemp("twokinds") / "store"
    shutil.copytree(synth_store, root)
    for rec in (root / "records").iterdir():
        np.save(rec / "shading_gt.npy", np.load(rec / "shading.npy") + 1.0)
    return root


def _train_set(root, share, spatial=("shading",)):
    dm = EncodingsDataModule(root=str(root), spatial=list(spatial), resolution=32, exact_share=share)
    dm.setup()
    return dm.train_set


def _exact_fraction(ds, draws):
    est = ds.store.read(ds.ids[0], ["shading"])["shading"]
    hits = [float((ds[0]["spatial"] - torch.from_numpy(np.array(est)).permute(2, 0, 1)).mean()) for _ in range(draws)]
    assert all(abs(h) < 1e-6 or abs(h - 1.0) < 1e-6 for h in hits)  # one kind or the other, never a blend
    return float(np.mean([h > 0.5 for h in hits]))


def test_share_zero_serves_estimated_and_one_serves_exact(two_kind_store):
    torch.manual_seed(0)
    assert _exact_fraction(_train_set(two_kind_store, 0.0), 8) == 0.0
    assert _exact_fraction(_train_set(two_kind_store, 1.0), 8) == 1.0


def test_a_half_share_serves_both_kinds_about_half_the_time(two_kind_store):
    torch.manual_seed(0)
    frac = _exact_fraction(_train_set(two_kind_store, 0.5), 200)
    assert 0.4 < frac < 0.6  # binomial(200, .5): 4.2 standard deviations either side


def test_validation_keeps_the_estimated_inputs(two_kind_store):
    dm = EncodingsDataModule(root=str(two_kind_store), spatial=["shading"], resolution=32, exact_share=1.0)
    dm.setup()
    assert dm.val_set.exact_share == 0.0


def test_a_store_without_exact_counterparts_is_refused(two_kind_store):
    # "background" has no *_gt: asking for both kinds there would silently train on one.
    with pytest.raises(UserError, match=r"keeps no exact counterpart.*data.exact_share=0"):
        _train_set(two_kind_store, 0.5, spatial=("background",))


@pytest.mark.parametrize("share", [-0.1, 1.5])
def test_a_share_outside_zero_one_is_refused(two_kind_store, share):
    with pytest.raises(UserError, match=r"data.exact_share=.* is a probability"):
        EncodingsDataModule(root=str(two_kind_store), spatial=["shading"], exact_share=share)
