"""Checkpoint format: the recorded module class, plain hyperparameters, and pre-format-2 checkpoints still loading."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch

from difareli.lit import DiffusionModule, load_checkpoint
from difareli.checkpoints.format import upgrade_checkpoint
from difareli.checkpoints.loading import module_class, read_checkpoint

from tests.helpers import compose_train

DATA = Path(__file__).parents[1] / "fixtures"
#: Written by the pre-issue-9 code (commit 070dd75): a 3-step tiny DiFaReli run (modulate_skips=true, lr 3e-4,
#: weight decay 0.01, EMA decay 0.5), optimizer states dropped for size; the expected file holds fixed inputs
#: and the eps that code's load_checkpoint produced for them.
OLD = DATA / "old_format_tiny.ckpt"

pytestmark = pytest.mark.usefixtures("one_thread")


def test_old_format_checkpoint_loads_with_identical_outputs():
    raw = torch.load(OLD, map_location="cpu", weights_only=True)
    assert "spatial_type" in raw["hyper_parameters"] and "ns_mean" in raw["state_dict"]  # really the old format
    want = torch.load(DATA / "old_format_tiny_expected.pt", weights_only=True)
    loaded = load_checkpoint(OLD)
    cfg = loaded.config
    assert type(loaded.model) is DiffusionModule and loaded.global_step == 3
    assert cfg["spatial"] == {"type": "modulator", "modulate_skips": True}
    assert cfg["optimizer"] == {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": 3e-4, "weight_decay": 0.01}
    assert cfg["scheduler"] is None and cfg["adagn_out_silu"] is False
    assert not {"spatial_type", "modulate_skips", "lr", "weight_decay"} & set(cfg)
    assert torch.equal(loaded.stats["mean"], want["ns_mean"]) and torch.equal(loaded.model.ns_std, want["ns_std"])
    m = loaded.model
    with torch.no_grad():
        eps = m.denoiser(m.condition(want["spatial"], want["nonspatial"]))(want["x"], want["t"])
    # Equal to float rounding: the file was written on a CPU with AVX-512, whose convolution kernels sum in
    # another order than an AVX2-only CPU's (bit-equal there, ~1e-7 apart here); a wrong mapping is off by far more.
    torch.testing.assert_close(eps, want["eps"], rtol=1e-5, atol=1e-6)
    # The translation matters: read as an unmodulated-skip network the same weights give other outputs.
    other = DiffusionModule(**{**{k: v for k, v in cfg.items() if k != "compile"},
                               "spatial": {"type": "modulator", "modulate_skips": False}})
    other.load_state_dict(m.state_dict())
    with torch.no_grad():
        unmodulated = other.denoiser(other.condition(want["spatial"], want["nonspatial"]))(want["x"], want["t"])
    assert not torch.allclose(unmodulated, eps, rtol=1e-5, atol=1e-6)  # beyond the tolerance above


def test_upgrade_strips_stat_buffers_for_resuming():
    """Resuming from an old checkpoint: the module's hook removes the buffers the model no longer has."""
    raw = torch.load(OLD, map_location="cpu", weights_only=True)
    cfg = upgrade_checkpoint(copy.deepcopy(raw))["hyper_parameters"]
    model = DiffusionModule(**cfg)
    model.on_load_checkpoint(raw)
    model.load_state_dict(raw["state_dict"])  # strict: no ns_mean / ns_std left
    assert "ns_mean" not in raw["current_model_state"] and raw["difareli_format"] == 2
    assert upgrade_checkpoint(raw) is raw and raw["hyper_parameters"] == cfg  # idempotent


def test_module_class_allow_list(tmp_path):
    assert module_class("difareli.lit.diffusion.DiffusionModule") is DiffusionModule
    assert module_class("difareli.lit.student.StudentModule").__name__ == "StudentModule"  # registered, not imported
    for bad in ("os.system", "builtins.eval", "difareli.checkpoints.loading.load_checkpoint", "difareli"):
        with pytest.raises(ValueError, match="module class|not a LightningModule"):
            module_class(bad)
    ckpt = read_checkpoint(OLD)
    ckpt["difareli_module"] = "subprocess.Popen"
    torch.save(ckpt, tmp_path / "evil.ckpt")
    with pytest.raises(ValueError, match="subprocess.Popen"):
        load_checkpoint(tmp_path / "evil.ckpt")


def test_optimizer_and_warmup_schedule_from_config(tmp_path):
    """``model.optimizer`` / ``+model/scheduler=warmup`` are partials; the LR follows linear warm-up, then constant;
    the recorded hyperparameters are plain and re-create the same optimizer."""
    from hydra.utils import instantiate

    cfg = compose_train(tmp_path, ["model=difareli_pp", "model.preset=tiny", "model.optimizer.lr=2e-3",
                                   "+model/scheduler=warmup", "model.scheduler.total_iters=4"])
    dims = {"spatial_channels": 18, "nonspatial_dim": 3, "resolution": 32}
    stats = {"mean": [0.5, -1.0, 2.0], "std": [1.0, 0.25, 3.0]}
    model = instantiate(cfg.model, input_dims=dims, nonspatial_stats=stats)
    hp = dict(model.hparams)
    assert hp["optimizer"] == {"_target_": "torch.optim.adamw.AdamW", "lr": 2e-3, "weight_decay": 0.0,
                               "_partial_": True}
    assert hp["scheduler"]["_target_"].endswith("LinearLR") and hp["scheduler"]["total_iters"] == 4
    assert hp["nonspatial_stats"] == stats and torch.equal(model.ns_std, torch.tensor(stats["std"]))
    opts = model.configure_optimizers()
    opt, sched = opts["optimizer"], opts["lr_scheduler"]["scheduler"]
    assert isinstance(opt, torch.optim.AdamW) and opts["lr_scheduler"]["interval"] == "step"
    lrs = []
    for _ in range(7):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    want = [2e-3 * (1e-3 + (1 - 1e-3) * min(k, 4) / 4) for k in range(7)]
    assert lrs == pytest.approx(want, rel=1e-9)
    # Rebuilt from the plain hyperparameters (what load_checkpoint does): same optimizer settings.
    again = DiffusionModule(**{k: v for k, v in hp.items() if k != "compile"}).configure_optimizers()
    assert again["optimizer"].defaults["lr"] == 2e-3 and type(again["lr_scheduler"]["scheduler"]) is type(sched)


def test_relightable_interface_and_bad_stats():
    dims = {"spatial_channels": 6, "nonspatial_dim": 4, "resolution": 32}
    m = DiffusionModule(name="x", spatial_inputs=["shading", "background"], nonspatial_inputs=["cam", "shadow"],
                        input_dims=dims, net_overrides={"base_channels": 8, "channel_mult": [1], "norm_groups": 4,
                                                        "adagn_hidden": 8, "attention_resolutions": []})
    assert m.spatial_inputs == ["shading", "background"] and m.nonspatial_inputs == ["cam", "shadow"]
    assert m.consumes == ["shading", "background", "cam", "shadow"]
    assert m.hparams["spatial"] == {"type": "modulator"} and m.hparams["nonspatial_stats"]["std"] == [1.0] * 4
    assert "ns_mean" not in m.state_dict()  # constants, not weights: not averaged by the EMA callback
    # adagn_out_silu (default: the public code's trailing SiLU) reaches every MLP3; old checkpoints are built without.
    from difareli.nn.unet import MLP3

    last = {type(mlp[-1]).__name__ for mlp in m.net.modules() if isinstance(mlp, MLP3)}
    assert m.hparams["adagn_out_silu"] is True and last == {"SiLU"}
    old = load_checkpoint(OLD).model
    assert {type(mlp[-1]).__name__ for mlp in old.net.modules() if isinstance(mlp, MLP3)} == {"Linear"}
    with pytest.raises(ValueError, match="nonspatial_stats needs 4 means"):
        DiffusionModule(input_dims=dims, spatial_inputs=["shading", "background"],
                        nonspatial_stats={"mean": [0.0], "std": [1.0]})
    with pytest.raises(ValueError, match="model.optimizer must be a Hydra partial"):
        DiffusionModule(input_dims=dims, spatial_inputs=["shading", "background"],
                        optimizer={"lr": 1e-3})


def test_a_module_in_memory_as_a_loaded_checkpoint(tiny_checkpoint):
    # What the relight-metrics callback and the store-wide jobs hand the Relighter: the module itself (nothing
    # copied), with the config and statistics that loading its checkpoint gives.
    from difareli.checkpoints.loading import LoadedCheckpoint

    loaded = load_checkpoint(tiny_checkpoint("difareli_pp"))
    module = loaded.model
    module.hparams["compile"] = True  # as a run trained with compile=true records it
    live = LoadedCheckpoint.of_module(module, global_step=7)
    assert live.model is module and live.global_step == 7 and live.resolution == loaded.resolution
    assert "compile" not in live.config and live.config == loaded.config
    assert live.stats.keys() == loaded.stats.keys() and live.stats
    assert all(torch.equal(live.stats[k], loaded.stats[k]) for k in loaded.stats)
    assert LoadedCheckpoint.of_module(torch.nn.Linear(1, 1)).config == {}  # a module without hyperparameters
