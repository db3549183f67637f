"""A checkpoint's files and the resume check (difareli.checkpoints.format / .loading): a corrupt file is one line
naming it, never a hint to unpickle; a resumed run against another model config lists what differs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difareli.checkpoints.format import load_torch_file
from difareli.checkpoints.loading import check_resume
from difareli.errors import UserError


@pytest.fixture
def real_ckpt(tmp_path):
    path = tmp_path / "good.ckpt"
    torch.save({"state_dict": {"w": torch.arange(1000.0)}, "hyper_parameters": {"preset": "tiny"}}, path)
    return path


def test_corrupt_checkpoints_name_the_file(real_ckpt, tmp_path):
    data = real_ckpt.read_bytes()
    cases = {"random.ckpt": np.random.default_rng(0).bytes(5000), "truncated.ckpt": data[: len(data) // 2],
             "text.ckpt": b"hello\n", "empty.ckpt": b""}
    for name, blob in cases.items():
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(UserError) as e:
            load_torch_file(tmp_path / name)
        msg = str(e.value)
        assert msg.startswith(f"checkpoint {tmp_path / name} ({len(blob)} bytes) is not a readable PyTorch file")
        assert "weights_only=False" not in msg and "\n" not in msg
    assert torch.equal(load_torch_file(real_ckpt)["state_dict"]["w"], torch.arange(1000.0))


def test_load_checkpoint_uses_the_check(tmp_path):
    from difareli.lit import load_checkpoint

    bad = tmp_path / "last.ckpt"
    bad.write_bytes(b"\x00" * 100)
    with pytest.raises(UserError, match=f"checkpoint {bad} \\(100 bytes\\)"):
        load_checkpoint(bad)


def _module(model: str, nonspatial_dim: int):
    from difareli.lit import DiffusionModule

    spatial = ["shading", "background"] if model == "difareli" else ["shading", "shadow_map", "masks"]
    ns = ["shape", "cam", "identity", "shadow"] if model == "difareli" else ["shape", "cam", "identity"]
    return DiffusionModule(name=model, preset="tiny", spatial_inputs=spatial, nonspatial_inputs=ns,
                           input_dims={"spatial_channels": 6 if model == "difareli" else 18,
                                       "nonspatial_dim": nonspatial_dim, "resolution": 32})


def test_check_resume_lists_differing_hyperparameters(tmp_path):
    saved = _module("difareli_pp", 20)
    path = tmp_path / "pp.ckpt"
    torch.save({"state_dict": saved.state_dict(), "hyper_parameters": dict(saved.hparams)}, path)
    check_resume(path, _module("difareli_pp", 20))  # same config: no error
    with pytest.raises(UserError) as e:
        check_resume(path, _module("difareli", 21))
    msg = str(e.value)
    assert msg.count("\n") == 1 and "tensors differ" in msg
    assert "name: checkpoint 'difareli_pp', config 'difareli'" in msg
    assert "spatial_inputs: checkpoint ['shading', 'shadow_map', 'masks'], config ['shading', 'background']" in msg
