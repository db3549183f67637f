"""The difference method through the relight door: ``shadow_maps.compute`` relights through
``Relighter.relight_many`` and writes the same raw differences, in float, as the tensor-core path it replaced
(kept below as the reference), for a trained tiny DiFaReli and for a one-pass model."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from difareli.data.inputs import condition_tensors, image_to_tensor, read_record, relight_reads
from difareli.data.store import EncodingStore
from difareli.diffusion.relight import Inversion
from difareli.diffusion.spec import SamplerSpec
from difareli.jobs import shadow_maps as sm
from difareli.relight.core import invert_image, relight
from difareli.relight.relightable import OnePassRelightable, model_inputs
from difareli.render.retarget import retarget
from difareli.utils import imageops


@torch.no_grad()
def old_relight_pairs(model, records, c_min, c_max, spec, *, runtime=None, mean_matching=True, device="cpu"):
    """shadow_maps.relight_pairs as it was on the tensor core, before the relight door, the independent reference."""
    names = model_inputs(model)
    x0 = torch.stack([image_to_tensor(a["image"]) for a in records]).to(device)
    targets = [retarget(a, names, np.asarray(a["light"]), c) for a in records for c in (c_max, c_min)]
    tcond = condition_tensors(model, targets, device)
    if isinstance(model, OnePassRelightable):
        out = [relight(model, x0[i:i + 1], condition_tensors(model, [a], device),
                       tuple(None if v is None else v[2 * i:2 * i + 2] for v in tcond), runtime=runtime)
               for i, a in enumerate(records)]
        relit = torch.cat(out)
    else:
        inv = invert_image(model, x0, condition_tensors(model, records, device), spec, runtime=runtime,
                           mean_matching=mean_matching)
        pairs = Inversion(inv.x_T.repeat_interleave(2, 0), inv.spec,
                          None if inv.offsets is None else inv.offsets.repeat_interleave(2, 1))
        relit = relight(model, x0, None, tcond, spec, runtime=runtime, inversion=pairs)
    img = ((relit.float().clamp(-1, 1) + 1) / 2).cpu().numpy().astype(np.float64)
    y = imageops.luminance(np.moveaxis(img, 1, -1))
    return y[1::2] - y[0::2]


class OnePass(torch.nn.Module):
    """A one-pass model whose output depends on the image, the source's c and the target's c (a random conv)."""

    spatial_inputs: list = []
    nonspatial_inputs = ["shadow"]

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.conv = torch.nn.Conv2d(3, 3, 3, padding=1)

    def condition(self, spatial, nonspatial):
        return nonspatial

    def relight_once(self, x0, source, target):
        return torch.tanh(self.conv(x0) + (torch.sigmoid(target) - torch.sigmoid(source))[:, :, None, None])


@pytest.fixture
def store(synth_store, tmp_path):
    shutil.copytree(synth_store, tmp_path / "store")
    return EncodingStore.open(tmp_path / "store", durable=False)


def _old_differences(model, store, ids, spec, batch_size):
    c_min, c_max = sm.c_range(store)
    needed = relight_reads(model_inputs(model))
    out = []
    for i in range(0, len(ids), batch_size):  # the job's batches: the same records inverted together
        recs = [read_record(store, r, needed) for r in ids[i:i + batch_size]]
        out.extend(old_relight_pairs(model, recs, c_min, c_max, spec))
    return np.stack(out)


@pytest.mark.parametrize("kind", ["difareli", "one_pass"])
def test_the_job_through_the_door_writes_the_old_float_differences(kind, tiny_checkpoint, store, one_thread):
    from difareli.checkpoints.loading import load_checkpoint

    torch.manual_seed(0)
    model = load_checkpoint(tiny_checkpoint("difareli"), "cpu").model if kind == "difareli" else OnePass()
    spec = SamplerSpec(name="ddim", steps=3) if kind == "difareli" else None
    ids = store.ids()[:5]  # batches of 2, 2 and 1
    want = _old_differences(model, store, ids, spec, batch_size=2)
    rep = sm.compute(model, store, spec, provenance={"checkpoint": kind}, ids=ids, batch_size=2, threshold=0.01,
                     min_contrast=0, check_after=0, progress=False)
    got = np.stack([np.asarray(store.read(r, [rep.raw])[rep.raw], np.float64) for r in ids])
    assert rep.relit == 5 and got.shape == want.shape == (5, 32, 32)
    assert np.abs(want).max() > 1e-4  # the model responds to c: the match is not of two zero maps
    # Measured 5e-10 / 9e-10 (the float32 of the stored maps): far finer than a uint8 step (0.004), which the cuts
    # near 0.02 on these differences would feel.
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
