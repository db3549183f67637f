"""Relighter.identity: what a folder of relit photos records of the relighter (relight.batch): the weights by
content, not their file; the sampler, precision and mean matching, each a difference a rerun is refused on."""

from __future__ import annotations

import shutil

import pytest
import torch

from difareli.diffusion.spec import SamplerSpec
from difareli.relight.relighter import Relighter

pytestmark = pytest.mark.usefixtures("one_thread")


def test_the_same_weights_from_another_file_are_the_same_relighter(tiny_checkpoint, tmp_path):
    ckpt = tiny_checkpoint("difareli_pp")
    copy = shutil.copy(ckpt, tmp_path / "renamed.ckpt")
    spec = SamplerSpec(name="ddim", steps=4)
    a, b = Relighter(ckpt, spec), Relighter(copy, spec)
    assert a.identity() == b.identity()
    assert a.identity()["checkpoint"].startswith("weights:")
    assert a.identity()["sampler"] == spec.to_config() and a.identity()["mean_matching"] is True


def test_each_setting_and_each_weight_changes_the_identity(tiny_checkpoint):
    ckpt = tiny_checkpoint("difareli_pp")
    base = Relighter(ckpt, SamplerSpec(name="ddim", steps=4)).identity()
    others = {"sampler": Relighter(ckpt, SamplerSpec(name="ddim", steps=5)),
              "mean_matching": Relighter(ckpt, SamplerSpec(name="ddim", steps=4), mean_matching=False),
              "precision": Relighter(ckpt, SamplerSpec(name="ddim", steps=4),
                                     runtime={"precision": "fp32" if base["precision"] != "fp32" else "bf16"})}
    for key, other in others.items():
        got = other.identity()
        assert {k for k in got if got[k] != base[k]} == {key}
    moved = Relighter(ckpt, SamplerSpec(name="ddim", steps=4))
    with torch.no_grad():
        next(moved.model.parameters()).view(-1)[0] += 1e-3  # one weight
    assert moved.identity()["checkpoint"] != base["checkpoint"]
