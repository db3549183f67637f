"""The encoding registry (channels, tensors, light-dependence, re-rendering) and the Relightable core's doors:
in-memory records, one-pass models, and the single list of light-dependent encodings."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difareli.data import encodings
from difareli.lighting import sh
from difareli.data.encodings import ENCODINGS, NUM_MASK_PARTS
from difareli.errors import NonFiniteError
from difareli.lit import LoadedCheckpoint
from difareli.relight.relightable import DiffusionRelightable, OnePassRelightable, Relightable
from difareli.relight.core import relight
from difareli.relight.relighter import Relighter
from difareli.data.store import EncodingStore
from difareli.render.retarget import RENDERERS, retarget
from difareli.relight.targets import Targets

DIMS = {"H": 8, "W": 8, **encodings.PRODUCER_DIMS}


def test_light_dependence_is_declared_once_and_resolves():
    assert encodings.light_dependent() == ["light", "shadow", "shadow_map", "shading", "light_gt", "shading_gt",
                                           "shadow_gt", "shadow_map_gt"]
    for name in encodings.light_dependent():
        e = encodings.get(name)
        assert callable(RENDERERS[e.rerender])  # the renderer takes each kind from the registry, below it
        assert all(n in ENCODINGS for n in e.needs)
    assert encodings.rerender_needs(["shading", "masks"]) == ["normal"]
    assert encodings.rerender_needs(["shadow_map", "shading"]) == ["depth", "normal", "cam", "shadow"]
    assert not encodings.get("masks").light_dependent and encodings.get("masks").rerender is None


def test_channels_follow_the_schema_shapes():
    pp_spatial, pp_ns = ["shading", "shadow_map", "masks"], ["shape", "cam", "identity"]
    assert encodings.total_channels(pp_spatial, DIMS) == 3 + 1 + NUM_MASK_PARTS
    assert encodings.total_channels(pp_ns, DIMS) == DIMS["S"] + 3 + DIMS["D"]
    assert encodings.total_channels(["light"], DIMS) == 27 and encodings.channels("background", DIMS) == 3
    # Each encoding's tensor has exactly the channels it declares.
    arrays = {"shading": np.random.rand(8, 8, 3).astype(np.float32), "shadow_map": np.zeros((8, 8), np.float32),
              "masks": np.random.randint(0, NUM_MASK_PARTS, (8, 8)).astype(np.uint8),
              "background": np.full((8, 8, 3), 255, np.uint8), "shape": np.ones(DIMS["S"], np.float32),
              "light": np.arange(27, dtype=np.float32).reshape(9, 3)}
    for name, a in arrays.items():
        t = encodings.get(name).to_tensor(a)
        assert (t.shape[0] if t.ndim == 3 else t.numel()) == encodings.channels(name, DIMS), name
    onehot = encodings.get("masks").to_tensor(arrays["masks"])
    assert torch.equal(onehot.sum(0), torch.ones(8, 8)) and torch.equal(onehot.argmax(0).byte(),
                                                                        torch.from_numpy(arrays["masks"]))
    assert encodings.get("background").to_tensor(arrays["background"]).max() == 1.0  # uint8 -> [-1, 1]
    assert torch.equal(encodings.get("light").to_tensor(arrays["light"]), torch.arange(27.0))


def test_retarget_rerenders_only_light_dependent(synth_store):
    store = EncodingStore.open(synth_store)
    names = ["shading", "shadow_map", "masks", "shape", "light", "shadow"]
    arrays = {k: np.asarray(v) for k, v in store.read("s00006_l0", names + ["normal", "depth", "cam"]).items()}
    light = sh.yaw(arrays["light"].astype(np.float64), 90.0)
    out = retarget(arrays, names, light, shadow=-2.0)
    assert out["masks"] is arrays["masks"] and out["shape"] is arrays["shape"]
    np.testing.assert_array_equal(out["light"], light.astype(np.float32))
    np.testing.assert_array_equal(out["shadow"], [-2.0])
    n = arrays["normal"].astype(np.float64)
    ref = sh.shading_reference(light, n, mask=np.linalg.norm(n, axis=-1) > 0.5)
    np.testing.assert_allclose(out["shading"], ref, rtol=1e-6)
    # Own light, own c: the re-rendered shading reference is the stored one.
    own = retarget(arrays, names, arrays["light"].astype(np.float64))
    np.testing.assert_allclose(own["shading"], arrays["shading"], atol=1e-5)
    np.testing.assert_array_equal(own["shadow"], arrays["shadow"])


def test_retarget_many_equals_one_target_at_a_time(synth_store):
    """The batched march behind a video's targets gives each target exactly its own re-render."""
    from difareli.render.retarget import retarget_many

    store = EncodingStore.open(synth_store)
    names = ["shading", "shadow_map", "masks", "light", "shadow"]
    arrays = {k: np.asarray(v) for k, v in store.read("s00006_l0", names + ["normal", "depth", "cam"]).items()}
    pairs = [(sh.yaw(arrays["light"].astype(np.float64), a), c)
             for a, c in [(-80, 1.0), (0, None), (35, -2.0), (80, 3.0)]]
    many = retarget_many(arrays, names, pairs)
    assert len(many) == 4 and any(m["shadow_map"].any() for m in many)
    for got, (light, c) in zip(many, pairs):
        want = retarget(arrays, names, light, c)
        assert set(got) == set(want)
        for n in names:
            np.testing.assert_array_equal(got[n], want[n])


class OnePass(torch.nn.Module):
    """A one-pass 'student': output = image * (1 + mean target shading - mean source shading)."""

    spatial_inputs, nonspatial_inputs = ["shading"], []

    def condition(self, spatial, nonspatial):
        return spatial.mean(dim=(1, 2, 3))

    def relight_once(self, x0, source, target):
        return x0 * (1 + target - source)[:, None, None, None]


def test_one_pass_model_goes_through_the_same_door(synth_store):
    model = OnePass()
    assert isinstance(model, Relightable) and isinstance(model, OnePassRelightable)
    assert not isinstance(model, DiffusionRelightable)
    x0 = torch.full((1, 3, 4, 4), 0.5)
    src = (torch.zeros(1, 3, 4, 4), None)
    tgt = (torch.stack([torch.zeros(3, 4, 4), torch.full((3, 4, 4), 0.5)]), None)
    out = relight(model, x0, src, tgt)  # no sampler needed
    np.testing.assert_allclose(out[:, 0, 0, 0].numpy(), [0.5, 0.75])
    r = Relighter(LoadedCheckpoint(model, {}, {}, 0), None, device="cpu")
    assert r.inversion(r.source(EncodingStore.open(synth_store), "s00006_l0")) is None
    assert r.needed_encodings() == ["image", "light", "shading", "normal"]
    store = EncodingStore.open(synth_store)
    arrays = dict(r.source(store, "s00006_l0").arrays)
    own = r.relight(r.source_from_arrays(arrays), Targets.of([arrays["light"]]))[0]
    np.testing.assert_array_equal(own, arrays["image"])  # own light: unchanged image (within uint8 rounding)


def test_in_memory_record_relights_like_the_store_record(tiny_checkpoint, synth_store):
    store = EncodingStore.open(synth_store)
    r = Relighter(tiny_checkpoint("difareli_pp"), {"name": "ddim", "steps": 3}, device="cpu")
    arrays = dict(r.source(store, "s00006_l0").arrays)
    light = sh.yaw(arrays["light"].astype(np.float64), 45.0)
    from_store = r.relight(r.source(store, "s00006_l0"), Targets.of([light]))
    in_memory = r.relight(r.source_from_arrays({k: v.copy() for k, v in arrays.items()}), Targets.of([light]))
    np.testing.assert_array_equal(from_store, in_memory)
    bad = {**arrays, "image": arrays["image"].copy()}
    bad["shape"] = np.full_like(arrays["shape"], np.nan)
    with pytest.raises(NonFiniteError, match="in-memory record, encoding 'shape'"):
        r.relight(r.source_from_arrays(bad), Targets.of([light]))
