"""Relighter.relight_each: many sources, one target each, in batches (the door teacher pairs and other store-wide
jobs use): equal to relighting each source alone."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.data.store import EncodingStore
from difareli.diffusion.spec import SamplerSpec
from difareli.relight.relighter import Relighter
from difareli.relight.targets import Targets


def test_relight_each_equals_one_at_a_time(tiny_checkpoint, synth_store, one_thread):
    store = EncodingStore.open(synth_store)
    r = Relighter(tiny_checkpoint("difareli_pp"), SamplerSpec(name="ddim", steps=4), batch_size=2,
                  runtime={"precision": "fp32"})
    ids = store.ids()[:3]
    sources = [r.source(store, rid) for rid in ids]
    lights = [store.read(rid, ["light"])["light"] for rid in reversed(ids)]
    targets = Targets.of(lights, [-3.0, -2.0, -4.0])
    both = r.relight_each(sources, targets)
    alone = np.stack([r.relight(s, Targets.of([lights[k]], [targets.shadows[k]]))[0] for k, s in enumerate(sources)])
    assert both.shape == (3, *store.read(ids[0], ["image"])["image"].shape)
    assert np.abs(both.astype(int) - alone.astype(int)).max() <= 1  # batched convolutions round differently
    with pytest.raises(ValueError, match="one target per source"):
        r.relight_each(sources, Targets.of(lights[:2], [-3.0, -2.0]))
