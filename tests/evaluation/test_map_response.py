"""The map-response probe (issue 41): a record relit with its shadow map and with the map zeroed; a model that
darkens exactly inside its map by a known amount scores that amount, one that ignores its map scores 0."""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch

from difareli.data.store import EncodingStore
from difareli.evaluation import map_response as mr
from difareli.relight.relightable import OnePassRelightable


class Follows(torch.nn.Module):
    """A one-pass 'relighter': grey 0.5 ([-1, 1] units: 0), ``drop`` darker (luminance units) inside its map."""

    spatial_inputs = ["shadow_map"]
    nonspatial_inputs: list = []

    def __init__(self, drop: float):
        super().__init__()
        self.drop = drop

    def condition(self, spatial, nonspatial):
        return spatial

    def relight_once(self, x0, source, target):
        dark = (target > 0).float() * (2 * self.drop)  # [-1, 1] units
        return (0.0 - dark).expand(-1, 3, -1, -1)


def _relighter(model):
    assert isinstance(model, OnePassRelightable)
    return types.SimpleNamespace(model=model, device=torch.device("cpu"), spec=None, runtime=None, mean_matching=True,
                                 needed_encodings=lambda: ["image", "shadow_map", "depth", "normal", "cam", "light",
                                                           "shadow"])


def test_a_model_that_darkens_its_map_by_x_scores_x_and_one_that_ignores_it_0(synth_store):
    store = EncodingStore.open(synth_store)
    ids = mr.shadowed_records(store, store.ids(), share=0.02)
    assert ids, "the fixture store has no shadowed record"
    follows = [r for rid in ids[:3] for r in mr.respond(_relighter(Follows(0.1)), store, rid, kinds=("exact",))]
    ignores = [r for rid in ids[:3] for r in mr.respond(_relighter(Follows(0.0)), store, rid, kinds=("exact",))]
    for r in follows:
        assert r.darkening == pytest.approx(0.1, abs=2e-3) and r.inside == pytest.approx(0.1, abs=2e-3)
        assert r.real > 0 and 0 < r.map_share < 1
    assert all(r.darkening == pytest.approx(0.0, abs=1e-9) for r in ignores)
    s = mr.summarise(follows)["exact"]
    assert s["ratio"] == pytest.approx(0.1 / s["real"], rel=0.03) and s["records"] == len(follows)


def test_real_removal_is_what_the_shadow_took_from_a_linear_image():
    face = np.ones((4, 4), bool)
    visible = np.zeros((4, 4), bool)
    visible[:2] = True
    frac = np.where(visible, 0.5, 0.0).astype(np.float32)
    image = np.full((4, 4, 3), 100, np.uint8)  # a shadowed pixel kept half its light: unshadowed it was 200
    arrays = {"image": image, "shadow_fraction_gt": frac, "shadow_visible_gt": visible, "face_mask": face}
    assert mr.real_removal(arrays) == pytest.approx(100 / 255.0, rel=1e-6)
