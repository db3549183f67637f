"""Relighter.relight_many: many sources, each under its own targets, in batches (the door
store-wide jobs use: teacher pairs, shadow maps, the map-response probe): equal to relighting each source alone."""

from __future__ import annotations

import numpy as np
import pytest

from difareli.data.store import EncodingStore
from difareli.diffusion.spec import SamplerSpec
from difareli.relight.relighter import Relighter
from difareli.relight.targets import Targets


def test_relight_many_of_one_target_each_equals_one_at_a_time(tiny_checkpoint, synth_store, one_thread):
    store = EncodingStore.open(synth_store)
    r = Relighter(tiny_checkpoint("difareli_pp"), SamplerSpec(name="ddim", steps=4), batch_size=2,
                  runtime={"precision": "fp32"})
    ids = store.ids()[:3]
    sources = [r.source(store, rid) for rid in ids]
    lights = [store.read(rid, ["light"])["light"] for rid in reversed(ids)]
    targets = Targets.of(lights, [-3.0, -2.0, -4.0])
    both = r.relight_many(sources, [targets.take(k, k + 1) for k in range(3)])[:, 0]
    alone = np.stack([r.relight(s, Targets.of([lights[k]], [targets.shadows[k]]))[0] for k, s in enumerate(sources)])
    assert both.shape == (3, *store.read(ids[0], ["image"])["image"].shape)
    assert np.abs(both.astype(int) - alone.astype(int)).max() <= 1  # batched convolutions round differently
    with pytest.raises(ValueError, match="3 sources but 2 sets of targets: give one per source"):
        r.relight_many(sources, [targets.take(k, k + 1) for k in range(2)])


def test_relight_many_shares_each_inversion_and_equals_one_at_a_time(tiny_checkpoint, synth_store, one_thread):
    """3 sources x 2 targets each (one with given target maps) in batches of 2 sources: uint8 within a rounding
    step of relight() alone; the float images are the uint8 ones before rounding."""
    store = EncodingStore.open(synth_store)
    r = Relighter(tiny_checkpoint("difareli_pp"), SamplerSpec(name="ddim", steps=4), batch_size=2,
                  runtime={"precision": "fp32"})
    ids = store.ids()[:3]
    sources = [r.source(store, rid) for rid in ids]
    lights = [store.read(rid, ["light"])["light"] for rid in ids]
    hw = store.read(ids[0], ["image"])["image"].shape[:2]
    square = np.zeros((2, *hw), np.float32)
    square[0, 8:20, 8:20] = 0.8
    targets = [Targets.of([lights[(k + 1) % 3], lights[(k + 2) % 3]], [-3.0 - k, -1.0],
                          maps=square if k == 1 else None) for k in range(3)]
    many = r.relight_many(sources, targets)
    floats = r.relight_many(sources, targets, as_float=True)
    alone = np.stack([r.relight(s, t) for s, t in zip(sources, targets)])
    assert many.shape == floats.shape == (3, 2, *hw, 3) and many.dtype == np.uint8 and floats.dtype == np.float32
    assert np.abs(many.astype(int) - alone.astype(int)).max() <= 1  # batched convolutions round differently
    assert np.abs(floats * 255 - many).max() <= 0.5 + 1e-3
    assert np.abs(many[:, 1].astype(int) - many[:, 0].astype(int)).max() > 1  # other targets: other images
    with pytest.raises(ValueError, match="as many targets each"):
        r.relight_many(sources[:2], [targets[0], Targets.of(lights[:1], [-2.0])])
    with pytest.raises(ValueError, match="one per source"):
        r.relight_many(sources, targets[:2])
    with pytest.raises(ValueError, match="at the source's resolution"):  # check_inputs, for each pair
        r.relight_many(sources[:1], [Targets.of(lights[:2], [-2.0, -1.0], maps=np.zeros((2, 8, 8)))])


def test_implausible_target_lights_are_said_in_terms_of_the_light():
    """A light with a negative ambient, or 50x the source's own, is named as the light's fault (not the sampler's);
    the source's own light is not flagged; no normals: nothing judged."""
    import numpy as np

    from difareli.lighting import sh
    from difareli.lighting.plausible import implausible_lights

    yy, xx = np.mgrid[-1:1:32j, -1:1:32j]
    zz = np.sqrt(np.clip(1 - xx ** 2 - yy ** 2, 0, None))
    normal = np.stack([xx, yy, zz], -1)
    normal[zz == 0] = 0  # off the face: unknown normals
    own = sh.directional_light([0.3, 0.2, 1.0], 1.0)
    own[0] += 0.8  # an ambient term
    dark = own.copy()
    dark[0] = -2.0  # negative ambient: negative irradiance over most of the face
    arrays = {"normal": normal, "light": own}
    said = implausible_lights(arrays, np.stack([own, dark, 50 * own]))
    assert set(said) == {1, 2}
    assert "negative irradiance" in said[1] and "ambient" in said[1]
    assert "50x brighter" in said[2] and "scale the light down" in said[2]
    assert implausible_lights({"light": own}, np.stack([dark])) == {}
