"""Paper ablation variants: ControlNet / CN-mod, cross-attention, the Table II/IV configs and
difareli-ablate's table."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml

from difareli.cli.ablate import merged_table, row_dir, table_rows, write_table
from difareli.diffusion.spec import PRESETS, SamplerSpec
from difareli.nn import build_network
from difareli.nn.controlnet import ControlNet
from difareli.nn.nonspatial import ContextTokens, CrossAttentionBlock
from difareli.data.inputs import condition_tensors
from difareli.relight.relightable import model_inputs
from difareli.relight.core import relight
from difareli.data.store import EncodingStore
from difareli.evaluation.tables import Record, write_records
from difareli.render.retarget import retarget

from tests.helpers import CONF, compose_train

#: The model configs this issue adds or re-bases (Table IV rows, Table II rows, background ablation).
NEW_MODELS = sorted(str(p.relative_to(CONF / "model").with_suffix("")) for d in ("mechanism", "ablation")
                    for p in (CONF / "model" / d).glob("*.yaml"))


def _randomize(module: torch.nn.Module, seed: int = 0, skip: tuple[str, ...] = ()) -> None:
    """Random weights everywhere (zero-initialised outputs too, so the network is not trivially zero), except
    parameters whose name contains one of ``skip``."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in module.named_parameters():
            if not any(s in name for s in skip):
                p.copy_(torch.randn(p.shape, generator=g) * 0.05)


def _cn_net(mod: bool, nonspatial: str = "adagn"):
    torch.manual_seed(0)
    return build_network("tiny", {"type": "controlnet", "mod": mod}, 5, 10,
                         nonspatial=nonspatial if nonspatial == "adagn" else {"type": nonspatial},
                         nonspatial_widths=[7, 3])


@pytest.mark.parametrize("mod", [False, True])
@pytest.mark.parametrize("nonspatial", ["adagn", "crossattn"])
def test_controlnet_at_init_changes_nothing(mod, nonspatial, one_thread):
    net = _cn_net(mod, nonspatial).eval()
    # Random UNet and ControlNet weights; only the ControlNet's zero convolutions keep their zero init.
    _randomize(net, skip=("zero_conv", "hint_block.6"))
    x, t = torch.randn(2, 3, 16, 16), torch.tensor([10, 700])
    spatial, vec = torch.randn(2, 5, 16, 16), torch.randn(2, 10)
    cond = net.condition(spatial, vec)
    with torch.no_grad():
        with_cn = net(x, t, cond)
        plain = net.unet(x, t, cond.nonspatial)  # the same UNet without the spatial hooks
        assert plain.abs().mean() > 1e-3  # a network that is not trivially zero
        assert torch.equal(with_cn, plain)
        # The same check can fail: one non-zero zero-conv changes the output.
        net.spatial.zero_convs[1].bias.fill_(0.1)
        assert not torch.allclose(net(x, t, cond), plain)


def test_controlnet_copies_the_encoder_and_needs_every_step():
    net = _cn_net(False)
    cn = net.spatial
    for (n, p), (_, q) in zip(cn.input_blocks.named_parameters(), net.unet.input_blocks.named_parameters()):
        assert torch.equal(p, q), n
    # The hint encoder's work is cached per condition; the encoder copy depends on x_t and t at every step.
    _randomize(net, seed=1)
    hint = torch.randn(1, 5, 16, 16)
    state = cn.prepare(hint)
    emb = net.unet.time_embed(torch.randn(1, net.config.base_channels))
    x = torch.randn(1, 3, 16, 16)
    r1 = cn.step(x, emb, torch.randn(1, 10), state)
    r2 = cn.step(x + 0.1, emb, torch.randn(1, 10), state)
    assert len(r1) == net.unet.num_levels
    assert all(a.shape[1] == c for a, c in zip(r1, net.unet.encoder_channels))
    assert not torch.allclose(r1[-1], r2[-1])


def test_cn_mod_differs_only_by_first_zero_block():
    cn, mod = _cn_net(False).state_dict(), _cn_net(True).state_dict()
    only_cn = {k for k in cn if k not in mod}
    assert only_cn and all(k.startswith("spatial.hint_block.") for k in only_cn)
    assert not set(mod) - set(cn)
    differing = [k for k in mod if mod[k].shape != cn[k].shape]
    assert differing == ["spatial.input_blocks.0.0.weight"]
    # CN-mod's input conv takes the raw hint (5 channels) next to x_t (3).
    assert mod[differing[0]].shape[1] == cn[differing[0]].shape[1] + 5
    assert isinstance(_cn_net(True).spatial, ControlNet) and _cn_net(True).spatial.hint_block is None


def test_freeze_base_trains_only_the_controlnet():
    net = build_network("tiny", {"type": "controlnet", "freeze_base": True}, 5, 0)
    assert not any(p.requires_grad for p in net.unet.parameters())
    assert all(p.requires_grad for p in net.spatial.parameters())


def test_cross_attention_single_token_closed_form(one_thread):
    block = CrossAttentionBlock(8, context_dim=6, num_heads=2, groups=4)
    _randomize(block, seed=2)
    h, ctx = torch.randn(2, 8, 4, 4), torch.randn(2, 1, 6)
    # One token: every softmax weight is 1, so the output is h + proj_out(V ctx), the same at every pixel.
    v = block.kv(ctx)[..., 8:]  # [B, 1, C], heads concatenated in channel order
    want = h + (block.proj_out.weight[..., 0] @ v[:, 0, :, None] + block.proj_out.bias[:, None])[..., None]
    torch.testing.assert_close(block(h, None, ctx), want.expand_as(h), rtol=1e-5, atol=1e-5)


def test_cross_attention_depends_on_every_token_and_is_permutation_aware(one_thread):
    block = CrossAttentionBlock(8, context_dim=6, num_heads=2, groups=4)
    _randomize(block, seed=3)
    h, ctx = torch.randn(1, 8, 4, 4), torch.randn(1, 5, 6)
    out = block(h, None, ctx)
    for i in range(ctx.shape[1]):
        bumped = ctx.clone()
        bumped[:, i] += 1.0
        assert (block(h, None, bumped) - out).abs().max() > 1e-4, f"token {i} is ignored"
    # Attention alone treats tokens as a set ...
    torch.testing.assert_close(block(h, None, ctx[:, [4, 2, 0, 1, 3]]), out, rtol=1e-5, atol=1e-6)
    # ... the tokens carry which encoding they came from: swapping two equally wide encodings changes them.
    tokens = ContextTokens([3, 3], context_dim=6, tokens_per_input=2)
    v = torch.randn(1, 6)
    swapped = torch.cat([v[:, 3:], v[:, :3]], dim=1)
    assert tokens(v).shape == (1, 4, 6)
    assert not torch.allclose(block(h, None, tokens(v)), block(h, None, tokens(swapped)))


def test_cross_attention_replaces_adagn_mlps_everywhere():
    adagn = build_network("tiny", "modulator", 5, 10).parameter_counts()
    ca = build_network("tiny", "modulator", 5, 10, nonspatial={"type": "crossattn"},
                       nonspatial_widths=[7, 3])
    counts = ca.parameter_counts()
    assert adagn["crossattn"] == 0 and adagn["mlps"] > 0
    assert counts["mlps"] == 0 and counts["crossattn"] > 0
    assert counts["unet"] == adagn["unet"] and counts["spatial"] == adagn["spatial"]
    # One cross-attention layer after every residual block of the UNet (encoder, middle, decoder).
    n_res = sum(type(m).__name__ == "ResBlock" for m in ca.unet.modules())
    n_ca = sum(isinstance(m, CrossAttentionBlock) for m in ca.unet.modules())
    assert n_ca == n_res - 1  # the middle block: ResBlock, attention, cross-attention, ResBlock


@pytest.mark.parametrize("model", NEW_MODELS)
def test_model_config_trains_one_step_and_relights_with_every_sampler(model, synth_store, tmp_path, one_thread):
    import hydra

    from difareli.lit.datamodule import EncodingsDataModule

    cfg = compose_train(tmp_path, [f"data.root={synth_store}", "data.resolution=32", "data.synth=null",
                                   f"model={model}", "model.preset=tiny"])
    dm = EncodingsDataModule(root=str(synth_store), spatial=list(cfg.model.spatial_inputs),
                             nonspatial=list(cfg.model.nonspatial_inputs), resolution=32, batch_size=2,
                             num_workers=0)
    mean, std = dm.nonspatial_stats()
    torch.manual_seed(0)
    module = hydra.utils.instantiate(cfg.model, input_dims=dm.input_dims(),
                                     nonspatial_stats={"mean": mean.tolist(), "std": std.tolist()})
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    opt = module.configure_optimizers()
    opt = opt["optimizer"] if isinstance(opt, dict) else opt
    before = [p.detach().clone() for p in module.net.parameters()]
    loss = module.diffusion_loss(batch)
    loss.backward()
    opt.step()
    assert math.isfinite(loss.item())
    assert any(not torch.equal(a, p) for a, p in zip(before, module.net.parameters()))
    module.eval()
    store = EncodingStore.open(synth_store)
    rid = store.ids()[0]
    names = list(dict.fromkeys(["image", "light", *model_inputs(module), "normal", "depth", "cam", "shadow"]))
    arrays = {k: np.asarray(v) for k, v in store.read(rid, [n for n in names if store.available(n)]).items()}
    x0 = torch.from_numpy(arrays["image"].copy()).permute(2, 0, 1)[None].float() / 127.5 - 1
    target = retarget(arrays, model_inputs(module), np.asarray(store.read(store.ids()[1], ["light"])["light"]), None)
    for name in PRESETS:
        out = relight(module, x0, condition_tensors(module, [arrays]), condition_tensors(module, [target]),
                      SamplerSpec.preset(name, steps=2))
        assert out.shape == (1, 3, 32, 32) and torch.isfinite(out).all(), name


@pytest.mark.slow  # Hydra multiruns: the default run has to finish in minutes at load 4
def test_table_multiruns_compose_with_one_row_per_config(tmp_path):
    for n, expected in ((4, 5), (2, 8)):
        models, labels, caption = table_rows(n)
        assert len(models) == expected and len(set(models)) == expected
        assert set(labels) == set(models), "every row has a label and every label a row"
        cfg = compose_train(tmp_path, [f"experiment=table{n}", "debug=fdr"], )
        assert cfg.model.preset == "tiny" and cfg.trainer.fast_dev_run
        for m in models:  # each row composes with the experiment
            row = compose_train(tmp_path, [f"experiment=table{n}", f"model={m}"])
            assert row.model._target_ == "difareli.lit.DiffusionModule"
    # Table IV is DiFaReli++ with its two components swapped; Table II rows are on the DiFaReli base.
    rows4 = {m: compose_train(tmp_path, ["experiment=table4", f"model={m}"]).model for m in table_rows(4)[0]}
    assert {(r.spatial.type, r.spatial.get("mod", False), r.nonspatial.type) for r in rows4.values()} == {
        ("controlnet", False, "crossattn"), ("controlnet", False, "adagn"), ("controlnet", True, "crossattn"),
        ("modulator", False, "crossattn"), ("modulator", False, "adagn")}
    assert all(list(r.spatial_inputs) == ["shading", "shadow_map", "masks"] for r in rows4.values())
    c = compose_train(tmp_path, ["model=ablation/no_shape_cam_identity"]).model
    assert list(c.nonspatial_inputs) == ["shadow"] and list(c.spatial_inputs) == ["shading", "background"]


def test_ablate_table_has_one_row_per_config_in_paper_order(tmp_path):
    models, labels, caption = table_rows(4)
    rng = np.random.default_rng(0)
    dirs = {}
    for i, m in enumerate(models):
        d = row_dir(tmp_path, m) / "bench"
        d.mkdir(parents=True)
        write_records(d / "metrics_per_image.csv",
                      [Record(m, p, f"r{j}", 0.1 * i + rng.random() * 0.01, 0.01, 0.05, 1.0)
                       for p in ("same", "different") for j in range(3)])
        dirs[m] = d
    table = merged_table(dirs, labels)
    assert table.methods == [labels[m] for m in models]
    assert table.cells[(labels[models[2]], "same")]["dssim"].n == 3
    paths = write_table(table, tmp_path / "out", caption)
    rows = paths["csv"].read_text().splitlines()
    assert len(rows) == 1 + len(models)
    md = paths["md"].read_text()
    assert all(labels[m] in md for m in models) and "a) CN / CA" in paths["tex"].read_text().replace("\\", "")


@pytest.mark.slow
def test_multirun_table4_fast_dev_run_every_row(synth_store, tmp_path):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "difareli.cli.train", "-m", "experiment=table4", "debug=fdr",
           f"data.root={synth_store}", "data.resolution=32", "data.synth=null", "data.num_workers=0",
           f"hydra.sweep.dir={tmp_path / 'sweep'}", f"paths.log_dir={tmp_path}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.is_dir())
    assert runs == [str(i) for i in range(len(table_rows(4)[0]))]
    for r in runs:
        chosen = yaml.safe_load((tmp_path / "sweep" / r / ".hydra" / "overrides.yaml").read_text())
        assert any(o.startswith("model=") for o in chosen)


@pytest.mark.slow
def test_ablate_end_to_end_resumes(synth_store, tmp_path):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "difareli.cli.ablate", "table=4", "steps=2", "limit=1", "sampler_steps=2",
           f"store={synth_store}", f"out_dir={tmp_path / 'abl'}", "rows=[mechanism/cnmod_ca,difareli_pp]",
           "train_overrides=['data.num_workers=0','data.batch_size=2','trainer.val_check_interval=2',"
           "'trainer.limit_val_batches=1']", f"paths.log_dir={tmp_path}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    csv = (tmp_path / "abl" / "table.csv").read_text().splitlines()
    assert len(csv) == 3 and (tmp_path / "abl" / "figure.png").is_file()
    again = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert again.returncode == 0 and "difareli.cli.train" not in again.stdout  # nothing retrained
    # Rerun with other steps into the same out_dir: refused (exit 2, naming steps), not the old table reprinted.
    other = subprocess.run([c if c != "steps=2" else "steps=3" for c in cmd], capture_output=True, text=True, env=env,
                           timeout=600)
    assert other.returncode == 2 and "steps: 2 there, 3 now" in other.stderr, other.stderr[-2000:]
    assert "difareli.cli.train" not in other.stdout
