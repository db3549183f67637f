"""Importing the authors' DiFaReli checkpoints (difareli.official.weights, difareli-import-checkpoint).

The official state dicts here are built from the official layout as its code defines it (names and shapes of
``UNetModel_SpatialCondition_Hadamart`` / ``EncoderUNet_SpatialCondition``, written out below, values random), and
an independent functional forward of that layout (legacy per-head q/k/v split, Hadamart gates before each block,
unmodulated skips, ``cond_params`` in the official order) is the oracle for the converted network.
"""

from __future__ import annotations

import inspect
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from difareli.official import weights as official
from difareli.official.config import PARAM_WIDTHS, read_config
from difareli.cli.import_checkpoint import main as cli_main
from difareli.errors import UserError
from difareli.lit import load_checkpoint
from difareli.checkpoints.loading import read_checkpoint

MC, MULT, NRES, RES, ATTN, HEADS, PROJ = 32, (1, 2), 1, 16, 8, 2, 16
SELECTOR = ["shape", "pose", "exp", "cam", "faceemb", "shadow"]
#: The architecture keys both official networks share (the Modulator mirrors the UNet's first half).
ARCH = (f"  image_size: {RES}\n  num_channels: {MC}\n  channel_mult: '1,2'\n  num_res_blocks: {NRES}\n"
        f"  attention_resolutions: '{ATTN}'\n  num_heads: {HEADS}\n  use_new_attention_order: NEW\n")
YAML = ("img_model:\n  name: ImgCond\n  arch: UNetCond_SpatialCondition_Hadamart\n" + ARCH
        + f"  conditioning: True\n  condition_proj_dim: {PROJ}\n  hadamart_prep: Tanh\n"
        + "param_model:\n  params_selector: SELECTOR\n"
        + "img_cond_model:\n  apply: True\n  arch: EncoderUNet_SpatialCondition\n" + ARCH
        + "  in_image: [deca_masked_face_images_woclip, faceseg_nohead]\n  override_cond: spatial_latent\n"
        + "  prep_image: [null, null]\n")


# ---------------------------------------------------------------------------------------------- the official layout
def _res(sd, p, ch, out, emb, cond):
    sd[p + "in_layers.0.weight"], sd[p + "in_layers.0.bias"] = (ch,), (ch,)
    sd[p + "in_layers.2.weight"], sd[p + "in_layers.2.bias"] = (out, ch, 3, 3), (out,)
    if cond:
        for i, (o, n) in enumerate([(PROJ, cond), (PROJ, PROJ), (out, PROJ)]):
            sd[f"{p}cond_proj_layers.{2 * i}.weight"], sd[f"{p}cond_proj_layers.{2 * i}.bias"] = (o, n), (o,)
    if emb:
        sd[p + "emb_layers.1.weight"], sd[p + "emb_layers.1.bias"] = (2 * out, emb), (2 * out,)
    sd[p + "out_layers.0.weight"], sd[p + "out_layers.0.bias"] = (out,), (out,)
    sd[p + "out_layers.3.weight"], sd[p + "out_layers.3.bias"] = (out, out, 3, 3), (out,)
    if ch != out:
        sd[p + "skip_connection.weight"], sd[p + "skip_connection.bias"] = (out, ch, 1, 1), (out,)


def _attn(sd, p, ch):
    sd[p + "norm.weight"], sd[p + "norm.bias"] = (ch,), (ch,)
    sd[p + "qkv.weight"], sd[p + "qkv.bias"] = (3 * ch, ch, 1), (3 * ch,)
    sd[p + "proj_out.weight"], sd[p + "proj_out.bias"] = (ch, ch, 1), (ch,)


def official_layout(unet: bool, cond: int = 672, in_ch: int = 6) -> dict[str, tuple]:
    """Names -> shapes of the official UNet (``unet``) or Modulator; the UNet's layer 0 of input blocks 1.. and of
    the middle block is a parameter-free HadamartLayer."""
    sd, emb, off = {}, 4 * MC if unet else 0, 1 if unet else 0
    if unet:
        sd["time_embed.0.weight"], sd["time_embed.0.bias"] = (emb, MC), (emb,)
        sd["time_embed.2.weight"], sd["time_embed.2.bias"] = (emb, emb), (emb,)
    sd["input_blocks.0.0.weight"], sd["input_blocks.0.0.bias"] = (MC, 3 if unet else in_ch, 3, 3), (MC,)
    chans, ch, ds, i = [MC], MC, 1, 1
    for level, m in enumerate(MULT):
        for _ in range(NRES):
            _res(sd, f"input_blocks.{i}.{off}.", ch, m * MC, emb, cond if unet else 0)
            ch = m * MC
            if ds == RES // ATTN:
                _attn(sd, f"input_blocks.{i}.{off + 1}.", ch)
            chans.append(ch)
            i += 1
        if level != len(MULT) - 1:
            sd[f"input_blocks.{i}.{off}.op.weight"], sd[f"input_blocks.{i}.{off}.op.bias"] = (ch, ch, 3, 3), (ch,)
            chans.append(ch)
            ds, i = ds * 2, i + 1
    _res(sd, f"middle_block.{off}.", ch, ch, emb, cond if unet else 0)
    _attn(sd, f"middle_block.{off + 1}.", ch)
    _res(sd, f"middle_block.{off + 2}.", ch, ch, emb, cond if unet else 0)
    if not unet:
        return sd
    j = 0
    for level, m in reversed(list(enumerate(MULT))):
        for k in range(NRES + 1):
            _res(sd, f"output_blocks.{j}.0.", ch + chans.pop(), m * MC, emb, cond)
            ch, layer = m * MC, 1
            if ds == RES // ATTN:
                _attn(sd, f"output_blocks.{j}.1.", ch)
                layer = 2
            if level and k == NRES:
                sd[f"output_blocks.{j}.{layer}.conv.weight"] = (ch, ch, 3, 3)
                sd[f"output_blocks.{j}.{layer}.conv.bias"] = (ch,)
                ds //= 2
            j += 1
    sd["out.0.weight"], sd["out.0.bias"] = (ch,), (ch,)
    sd["out.2.weight"], sd["out.2.bias"] = (3, ch, 3, 3), (3,)
    return sd


def random_state(layout: dict[str, tuple], seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {k: (1.0 if len(s) == 1 and k.endswith("weight") else 0.0) + torch.randn(s, generator=g)
            * (0.1 if len(s) == 1 else 1 / math.prod(s[1:]) ** 0.5) for k, s in layout.items()}


# ---------------------------------------------------------------------------------------------- the official forward
def _gn(sd, p, x):
    return F.group_norm(x.float(), 32, sd[p + ".weight"], sd[p + ".bias"], 1e-5)


def _lin(sd, p, x):
    return F.linear(x, sd[p + ".weight"], sd[p + ".bias"])


def _conv(sd, p, x, **kw):
    w = sd[p + ".weight"]
    return (F.conv1d if w.ndim == 3 else F.conv2d)(x, w, sd[p + ".bias"], **kw)


def _res_f(sd, p, x, emb=None, cond=None):
    h = _conv(sd, p + "in_layers.2", F.silu(_gn(sd, p + "in_layers.0", x)), padding=1)
    if emb is not None:
        scale, shift = _lin(sd, p + "emb_layers.1", F.silu(emb))[..., None, None].chunk(2, 1)
        k = cond
        for i in (0, 2, 4):
            k = F.silu(_lin(sd, f"{p}cond_proj_layers.{i}", k))
        h = (_gn(sd, p + "out_layers.0", h) * (1 + scale) + shift) * k[..., None, None]
    else:
        h = _gn(sd, p + "out_layers.0", h)
    h = _conv(sd, p + "out_layers.3", F.silu(h), padding=1)
    return (_conv(sd, p + "skip_connection", x) if p + "skip_connection.weight" in sd else x) + h


def _attn_f(sd, p, x, new_order):
    b, c, hh, ww = x.shape
    flat = x.reshape(b, c, -1)
    qkv, d = _conv(sd, p + "qkv", _gn(sd, p + "norm", flat)), c // HEADS
    if new_order:
        q, k, v = (t.reshape(b * HEADS, d, -1) for t in qkv.chunk(3, 1))
    else:
        q, k, v = qkv.reshape(b * HEADS, 3 * d, -1).split(d, 1)
    s = 1 / math.sqrt(math.sqrt(d))
    a = torch.einsum("bts,bcs->bct", torch.einsum("bct,bcs->bts", q * s, k * s).softmax(-1), v)
    return (flat + _conv(sd, p + "proj_out", a.reshape(b, c, -1))).reshape(b, c, hh, ww)


def _block(sd, p, h, emb, cond, new_order):
    """The layers under prefix ``p`` (``input_blocks.3.`` ...), in index order, as the official Sequential runs."""
    idx = sorted({int(k[len(p):].split(".")[0]) for k in sd if k.startswith(p)})
    for j in idx:
        q = f"{p}{j}."
        if q + "weight" in sd:  # input_blocks.0.0: the input conv
            h = _conv(sd, q[:-1], h, padding=1)
        elif q + "in_layers.0.weight" in sd:
            h = _res_f(sd, q, h, emb, cond)
        elif q + "qkv.weight" in sd:
            h = _attn_f(sd, q, h, new_order)
        elif q + "op.weight" in sd:
            h = _conv(sd, q + "op", h, stride=2, padding=1)
        else:
            h = _conv(sd, q + "conv", F.interpolate(h, scale_factor=2, mode="nearest"), padding=1)
    return h


def official_eps(unet, mod, x, t, img, cond, new_order=False):
    """eps of the official model: Modulator outputs m_i gate the UNet as h * tanh(m_i) before each next block."""
    lat, h = [], img
    n_in = len({k.split(".")[1] for k in mod if k.startswith("input_blocks.")})
    for i in range(n_in):
        h = _block(mod, f"input_blocks.{i}.", h, None, None, new_order)
        lat.append(h)
    lat.append(_block(mod, "middle_block.", h, None, None, new_order))
    half = MC // 2
    freqs = torch.exp(-math.log(10000) * torch.arange(half, dtype=torch.float32) / half)
    args = t.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], -1)
    emb = _lin(unet, "time_embed.2", F.silu(_lin(unet, "time_embed.0", emb)))
    h = _block(unet, "input_blocks.0.", x, emb, cond, new_order)
    hs = [h]
    for i in range(1, n_in):
        h = _block(unet, f"input_blocks.{i}.", h * lat[i - 1].tanh(), emb, cond, new_order)
        hs.append(h)
    h = _block(unet, "middle_block.", h * lat[-2].tanh(), emb, cond, new_order) * lat[-1].tanh()
    for j in range(len({k.split(".")[1] for k in unet if k.startswith("output_blocks.")})):
        h = _block(unet, f"output_blocks.{j}.", torch.cat([h, hs.pop()], 1), emb, cond, new_order)
    return _conv(unet, "out.2", F.silu(_gn(unet, "out.0", h)), padding=1)


# ---------------------------------------------------------------------------------------------- fixtures
def write_run(tmp_path: Path, *, new_order=False, selector=SELECTOR, drop=None, seed=0) -> tuple[Path, Path, dict]:
    cond = sum(PARAM_WIDTHS[p] for p in selector)
    unet, mod = random_state(official_layout(True, cond), seed), random_state(official_layout(False), seed + 1)
    if drop:
        del unet[drop]
    run = tmp_path / "run"
    run.mkdir(exist_ok=True)
    torch.save(unet, run / "ImgCond_ema_0.9999_000100.pt")
    torch.save(mod, run / "ImgEncoder_ema_0.9999_000100.pt")
    cfg = tmp_path / "official.yaml"
    cfg.write_text(YAML.replace("NEW", str(new_order)).replace("SELECTOR", str(selector)))
    return run, cfg, {"unet": unet, "mod": mod}


def inputs(b: int, seed: int = 5):
    g = torch.Generator().manual_seed(seed)
    parts = {k: torch.randn(b, w, generator=g) for k, w in PARAM_WIDTHS.items()}
    x, img = torch.randn(b, 3, RES, RES, generator=g), torch.randn(b, 6, RES, RES, generator=g)
    ours = torch.cat([parts["shape"], parts["exp"], parts["pose"], parts["cam"], parts["faceemb"], parts["shadow"]], 1)
    return x, img, parts, ours


# ---------------------------------------------------------------------------------------------- conversion
@pytest.mark.parametrize("new_order", [False, True])
def test_imported_network_is_the_official_one(tmp_path, new_order):
    run, cfg, sd = write_run(tmp_path, new_order=new_order)
    summary = official.import_checkpoint(run, cfg, tmp_path / "ours.ckpt")
    assert summary["max_abs_diff"] == 0.0 and summary["step"] == 100
    assert summary["parameters"] == sum(v.numel() for part in sd.values() for v in part.values())
    model = load_checkpoint(tmp_path / "ours.ckpt").model
    assert model.spatial_inputs == ["shading", "background"]
    assert model.nonspatial_inputs == ["shape", "cam", "identity", "shadow"]
    for b in (1, 2):
        x, img, parts, ours = inputs(b)
        t = torch.tensor([0, 731][:b])
        with torch.no_grad():
            want = official_eps(sd["unet"], sd["mod"], x, t, img, torch.cat([parts[k] for k in SELECTOR], 1),
                                new_order)
            got = model.net(x, t, model.condition(img, ours))
        assert (got - want).abs().max() < 1e-5 * want.abs().max()


def test_mapped_network_equals_ours_loaded_normally(tmp_path):
    _, cfg, sd = write_run(tmp_path)
    ckpt, module = official.convert(sd["unet"], sd["mod"], read_config(cfg))
    torch.save(ckpt, tmp_path / "ours.ckpt")
    loaded = load_checkpoint(tmp_path / "ours.ckpt").model
    x, img, _, ours = inputs(2)
    t = torch.tensor([10, 990])
    with torch.no_grad():
        a, b = module.net(x, t, module.condition(img, ours)), loaded.net(x, t, loaded.condition(img, ours))
    assert float((a - b).abs().max()) == 0.0


def test_parts_the_checkpoint_never_saw_get_zero_weights(tmp_path):
    selector = ["shape", "cam", "faceemb", "shadow"]
    run, cfg, sd = write_run(tmp_path, selector=selector)
    official.import_checkpoint(run, cfg, tmp_path / "ours.ckpt")
    model = load_checkpoint(tmp_path / "ours.ckpt").model
    x, img, parts, ours = inputs(1)
    with torch.no_grad():
        want = official_eps(sd["unet"], sd["mod"], x, torch.tensor([400]), img,
                            torch.cat([parts[k] for k in selector], 1))
        got = model.net(x, torch.tensor([400]), model.condition(img, ours))  # exp and pose values are ignored
    assert (got - want).abs().max() < 1e-5 * want.abs().max()


def test_store_layout_default_is_the_importers():
    from difareli.official import importers

    default = inspect.signature(importers.import_difareli).parameters["shape_parts"].default
    assert tuple(default) == official.STORE_SHAPE_PARTS


# ---------------------------------------------------------------------------------------------- refusals
def run_cli(capsys, *argv) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        cli_main([str(a) for a in argv])
    return e.value.code, capsys.readouterr().err


def test_cli_writes_a_checkpoint_every_loader_takes(tmp_path, capsys):
    run, cfg, _ = write_run(tmp_path)
    assert cli_main([str(run / "ImgEncoder_ema_0.9999_000100.pt"), f"config={cfg}", f"out={tmp_path}/o.ckpt"]) == 0
    assert "max |eps difference| 0.0e+00" in capsys.readouterr().out
    assert read_checkpoint(tmp_path / "o.ckpt")["imported_from"]["unet"] == "ImgCond_ema_0.9999_000100.pt"


def test_official_file_as_checkpoint_names_the_import_command(tmp_path):
    run, _, _ = write_run(tmp_path)
    with pytest.raises(UserError, match="difareli-import-checkpoint .*ImgCond_ema_0.9999_000100.pt config="):
        load_checkpoint(run / "ImgCond_ema_0.9999_000100.pt")


def test_partial_file_is_refused_naming_the_tensor(tmp_path, capsys):
    run, cfg, _ = write_run(tmp_path, drop="middle_block.2.qkv.weight")
    code, err = run_cli(capsys, run, f"config={cfg}", f"out={tmp_path}/o.ckpt")
    assert code == 2 and "ImgCond_ema_0.9999_000100.pt lacks 1 tensor(s) (net.unet.middle_block.1.qkv.weight)" in err
    assert "partial" in err and not (tmp_path / "o.ckpt").exists()


def test_wrong_config_is_refused_naming_the_shape(tmp_path, capsys):
    run, cfg, _ = write_run(tmp_path)
    cfg.write_text(cfg.read_text().replace("condition_proj_dim: 16", "condition_proj_dim: 32"))
    code, err = run_cli(capsys, run, f"config={cfg}", f"out={tmp_path}/o.ckpt")
    assert code == 2 and "has shape (16, 672)" in err and "implies (32, 672)" in err


@pytest.mark.parametrize("what", ["bytes", "pickle", "ours", "no_encoder", "not_official_yaml", "arch"])
def test_bad_inputs_are_refused_in_one_or_two_lines(tmp_path, capsys, what):
    run, cfg, _ = write_run(tmp_path)
    unet = run / "ImgCond_ema_0.9999_000100.pt"
    expect = {"bytes": "not a readable PyTorch file", "pickle": "holds objects other than tensors",
              "ours": "is already a difareli checkpoint", "no_encoder": "no ImgEncoder_ema_0.9999_000100.pt beside it",
              "not_official_yaml": "is not an official DiFaReli config", "arch": "img_model.arch='UNet'"}[what]
    if what == "bytes":
        unet.write_bytes(os.urandom(300))
    elif what == "pickle":
        torch.save({"input_blocks.0.0.weight": torch.nn.Linear(2, 2)}, unet)
    elif what == "ours":
        official.import_checkpoint(run, cfg, tmp_path / "ours.ckpt")
        unet = tmp_path / "ours.ckpt"
    elif what == "no_encoder":
        (run / "ImgEncoder_ema_0.9999_000100.pt").unlink()
    elif what == "not_official_yaml":
        cfg.write_text("model: {preset: tiny}\n")
    else:
        cfg.write_text(cfg.read_text().replace("UNetCond_SpatialCondition_Hadamart", "UNet"))
    code, err = run_cli(capsys, unet, f"config={cfg}", f"out={tmp_path}/o.ckpt",
                        *(["encoder=" + str(run / "ImgEncoder_ema_0.9999_000100.pt")] if what == "ours" else []))
    assert code == 2 and expect in err and len(err.strip().splitlines()) <= 2, err


def test_usage_errors(capsys):
    code, err = run_cli(capsys, "a.pt", "config=x.yaml", "outt=o.ckpt")
    assert code == 2 and "unknown option 'outt'" in err


# ---------------------------------------------------------------------------------------------- OpenMP (item 5)
def test_console_entry_makes_openmp_passive_on_a_busy_machine_before_torch_loads():
    # A busy machine stood in for by other runnable threads the rule counts (64 or none), before torch loads.
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env["OMP_DISPLAY_ENV"] = "VERBOSE"  # libgomp prints the values it read when torch loaded it
    code = ("from difareli.utils import processes as p; "
            "p.runnable_elsewhere = lambda: {busy}; "
            "import difareli.cli.import_checkpoint, torch; torch.ones(8).sum()")
    read = {}
    for busy in (64.0, 0.0):
        out = subprocess.run([sys.executable, "-c", code.format(busy=busy)], env=env, capture_output=True, text=True,
                             check=True)
        if "GOMP_SPINCOUNT" not in out.stderr:
            pytest.skip("torch's OpenMP runtime here is not libgomp (nothing to read back)")
        read[busy] = out.stderr
    assert "GOMP_SPINCOUNT = '0'" in read[64.0] and "OMP_WAIT_POLICY = 'PASSIVE'" in read[64.0]
    # quiet: libgomp's own policy (it prints an unset policy as PASSIVE; its spin count tells them apart)
    assert "GOMP_SPINCOUNT = '300000'" in read[0.0]


def test_auto_precision_is_bf16_exactly_where_the_cpu_has_bf16():
    from difareli.runtime.core import Runtime

    flags = Path("/proc/cpuinfo").read_text() if os.path.exists("/proc/cpuinfo") else ""
    want = "bf16" if ("avx512_bf16" in flags or "amx_bf16" in flags) else "fp32"
    assert Runtime(device="cpu", precision="auto").precision == want
    assert Runtime.from_config({"device": "cpu", "precision": "auto"}) == Runtime(device="cpu", precision=want)
