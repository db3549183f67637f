"""The network: ADM UNet + AdaGN + Modulator/ConcatSpatial, presets, DiffusionNet (SPEC 4)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from difareli.nn import (
    AdaGN,
    ConcatSpatial,
    DiffusionNet,
    Modulator,
    UNetConfig,
    build_network,
    get_config,
    timestep_embedding,
)
from difareli.data.inputs import variant_widths
from difareli.nn.unet import MLP3, GroupNorm32, ResBlock

# (spatial_type, spatial_channels, nonspatial_dim)
# Input widths from the variants' conf/model files and the encoding registry (no hard-coded channel counts).
DIFARELI = ("modulator", *variant_widths("difareli"))  # shading + background; shape, cam, identity, shadow
DIFARELI_PP = ("modulator", *variant_widths("difareli_pp"))  # shading + shadow map + masks; shape, cam, identity
VARIANTS = {
    "difareli": DIFARELI,
    "difareli++": DIFARELI_PP,
    "concat": ("concat", 3, DIFARELI_PP[2]),
    "no_nonspatial": ("modulator", 6, 0),
    "unconditional": (None, 0, 0),
}


# Small tensors: one intra-op thread (conftest.one_thread) avoids OpenMP spin-waits on a shared CPU.
pytestmark = pytest.mark.usefixtures("one_thread")


def randomize(net: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Give zero-initialised parameters (ADM's zero convs, GN biases) random values so every path is exercised."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            if p.abs().max() == 0:
                p.copy_(0.05 * torch.randn(p.shape, generator=g))
    return net


def make(variant: str, preset: str = "tiny", seed: int = 0, spatial_options: dict | None = None,
         **kw) -> DiffusionNet:
    torch.manual_seed(seed)
    kind, sc, nd = VARIANTS[variant]
    spec = {"type": kind, **spatial_options} if spatial_options else kind
    return randomize(build_network(preset, spec, sc, nd, **kw), seed).eval()


def inputs(variant: str, b: int = 2, size: int = 16, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    _, sc, nd = VARIANTS[variant]
    x = torch.randn(b, 3, size, size, generator=g)
    spatial = torch.randn(b, sc, size, size, generator=g) if sc else None
    nonspatial = torch.randn(b, nd, generator=g) if nd else None
    return x, spatial, nonspatial


@pytest.mark.parametrize("variant,size", [(v, 32) for v in VARIANTS] + [("difareli", 64), ("difareli++", 64)])
def test_tiny_shapes(variant, size):
    net = make(variant)
    x, s, ns = inputs(variant, size=size)
    with torch.no_grad():
        eps = net(x, torch.tensor([0, 999]), net.condition(s, ns))
    assert eps.shape == (2, 3, size, size)
    assert torch.isfinite(eps).all() and eps.std() > 1e-3


def test_tiny_parameter_budget():
    counts = make("difareli").parameter_counts()
    assert 1_000_000 < counts["total"] < 3_000_000
    assert counts["total"] == counts["unet"] + counts["spatial"] + counts["mlps"]


@pytest.mark.parametrize("preset,unet_range", [("ffhq128", (80e6, 110e6)), ("ffhq256", (105e6, 145e6))])
def test_preset_param_counts_and_modulator_mirrors_encoder(preset, unet_range):
    kind, sc, nd = DIFARELI_PP
    with torch.device("meta"):
        net = build_network(preset, kind, sc, nd)
    counts = net.parameter_counts()
    assert unet_range[0] < counts["unet"] < unet_range[1], counts
    unet, cfg = net.unet, net.config
    # one MLP3 per residual block, 512 -> 512 hidden, output width = the block's channels
    resblocks = [m for m in unet.modules() if isinstance(m, ResBlock)]
    mlps = [m for m in unet.modules() if isinstance(m, MLP3)]
    assert len(mlps) == len(resblocks) == (cfg.num_res_blocks * len(cfg.channel_mult) + 2
                                           + (cfg.num_res_blocks + 1) * len(cfg.channel_mult))
    assert all(m[0].in_features == nd and m[2].in_features == 512 for m in mlps)
    # The Modulator is the UNet's first half minus everything time/non-spatial and with C_s input channels.
    enc = list(unet.input_blocks.parameters()) + list(unet.middle_block.parameters())
    adagn = [m for b in (unet.input_blocks, unet.middle_block) for m in b.modules() if isinstance(m, AdaGN)]
    time_and_k = sum(p.numel() for a in adagn for n, p in a.named_parameters() if not n.startswith("norm."))
    first_conv_delta = (3 - sc) * 9 * cfg.base_channels
    assert counts["spatial"] == sum(p.numel() for p in enc) - time_and_k - first_conv_delta
    assert net.spatial.num_levels == unet.num_levels == len(unet.encoder_channels)


def test_ffhq128_forward_16px():
    torch.manual_seed(0)
    net = build_network("ffhq128", *DIFARELI).eval()
    x, s, ns = torch.randn(1, 3, 16, 16), torch.randn(1, 6, 16, 16), torch.randn(1, 185)
    with torch.no_grad():
        assert net(x, torch.tensor([500]), net.condition(s, ns)).shape == (1, 3, 16, 16)


@pytest.mark.slow
def test_ffhq256_forward_32px():
    torch.manual_seed(0)
    net = build_network("ffhq256", *DIFARELI_PP).eval()
    x, s, ns = torch.randn(1, 3, 32, 32), torch.randn(1, DIFARELI_PP[1], 32, 32), torch.randn(1, DIFARELI_PP[2])
    with torch.no_grad():
        assert net(x, torch.tensor([500]), net.condition(s, ns)).shape == (1, 3, 32, 32)


def test_timestep_embedding_values():
    emb = timestep_embedding(torch.tensor([0, 10]), 8)
    assert torch.equal(emb[0], torch.tensor([1.0, 1, 1, 1, 0, 0, 0, 0]))
    freqs = torch.exp(-torch.log(torch.tensor(10000.0)) * torch.arange(4) / 4)
    torch.testing.assert_close(emb[1], torch.cat([torch.cos(10 * freqs), torch.sin(10 * freqs)]))


@pytest.mark.parametrize("scale_plus_one", [True, False])
def test_adagn_matches_equation(scale_plus_one):
    torch.manual_seed(0)
    c, e, d = 64, 16, 7
    layer = randomize(AdaGN(c, e, d, groups=32, scale_plus_one=scale_plus_one, hidden=24))
    with torch.no_grad():
        layer.norm.weight.normal_(1.0, 0.2)
        layer.norm.bias.normal_(0.0, 0.2)
    h, emb, ns = torch.randn(2, c, 5, 6) * 3 + 1, torch.randn(2, e), torch.randn(2, d)
    lin = layer.time[1]
    ts, tb = (F.silu(emb) @ lin.weight.T + lin.bias).chunk(2, dim=1)
    l1, l2, l3 = layer.mlp[0], layer.mlp[2], layer.mlp[4]
    k = F.silu(F.silu(ns @ l1.weight.T + l1.bias) @ l2.weight.T + l2.bias) @ l3.weight.T + l3.bias
    scale = 1 + ts if scale_plus_one else ts
    gn = F.group_norm(h, 32, layer.norm.weight, layer.norm.bias, eps=layer.norm.eps)
    want = k[..., None, None] * (scale[..., None, None] * gn + tb[..., None, None])
    got = layer(h, emb, ns)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    # the two forms differ by exactly k * GN(h), which is far from zero here
    layer.scale_plus_one = not scale_plus_one
    diff = (got - layer(h, emb, ns)) * (1 if scale_plus_one else -1)
    torch.testing.assert_close(diff, k[..., None, None] * gn, rtol=1e-4, atol=1e-5)
    assert diff.abs().max() > 0.1


def test_adagn_without_nonspatial_has_k_one():
    torch.manual_seed(0)
    layer = randomize(AdaGN(32, 8, 0))
    assert layer.mlp is None
    h, emb = torch.randn(2, 32, 4, 4), torch.randn(2, 8)
    ts, tb = layer.time(emb).chunk(2, dim=1)
    want = (1 + ts[..., None, None]) * F.group_norm(h, 32, layer.norm.weight, layer.norm.bias) + tb[..., None, None]
    torch.testing.assert_close(layer(h, emb), want)


def test_groupnorm32_statistics_in_float32():
    gn = GroupNorm32(4, 8)
    x = (torch.randn(2, 8, 3, 3) * 100 + 1000).bfloat16()
    y = gn(x)
    assert y.dtype == torch.bfloat16
    assert torch.equal(y, F.group_norm(x.float(), 4, gn.weight, gn.bias).bfloat16())


def test_groupnorm32_bf16_cpu_kernel_equals_the_float_path():
    """On a CPU a bf16 input takes the mixed-type kernel (no fp32 copy): output within one bf16 rounding of the
    explicit cast path, gradients of input and affine equal to float rounding."""
    torch.manual_seed(0)
    gn = GroupNorm32(8, 32)
    torch.nn.init.normal_(gn.weight)
    torch.nn.init.normal_(gn.bias)
    x = (torch.randn(4, 32, 16, 16) * 3 + 5).bfloat16().requires_grad_()
    y = gn(x)
    ref = F.group_norm(x.float(), 8, gn.weight, gn.bias, gn.eps).bfloat16()
    assert y.dtype == torch.bfloat16
    ulp = ref.float().abs().clamp_min(1e-3) * 2 ** -7  # one bf16 rounding step of each value
    assert ((y.float() - ref.float()).abs() <= ulp).all()
    assert (y != ref).float().mean() < 1e-3  # nearly all values identical
    g = torch.randn_like(y)
    gx, gw, gb = torch.autograd.grad(y, (x, gn.weight, gn.bias), g)
    rx, rw, rb = torch.autograd.grad(ref, (x, gn.weight, gn.bias), g)
    assert gx.dtype == torch.bfloat16 and gw.dtype == torch.float32
    assert torch.allclose(gx.float(), rx.float(), rtol=2 ** -7, atol=1e-2)
    assert torch.allclose(gw, rw, rtol=1e-4, atol=1e-3) and torch.allclose(gb, rb, rtol=1e-4, atol=1e-3)


def test_groupnorm32_channels_last_bf16_takes_the_cast_path():
    """A channels-last bf16 input (the inference copy's layout) takes the explicit cast path, bit for bit, in its
    layout: PyTorch's mixed kernel is many times slower on it at small sizes (16 x 16 px)."""
    torch.manual_seed(0)
    gn = GroupNorm32(32, 64)
    torch.nn.init.normal_(gn.weight)
    torch.nn.init.normal_(gn.bias)
    x = (torch.randn(2, 64, 16, 16) * 3 + 5).bfloat16().contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        y = gn(x)
    assert y.is_contiguous(memory_format=torch.channels_last) and y.dtype == torch.bfloat16
    assert torch.equal(y, F.group_norm(x.float(), 32, gn.weight, gn.bias, gn.eps).bfloat16())


def _capture(net):
    """Hooks recording each input block's output, the middle output and each decoder block's input."""
    rec: dict[str, list] = {"out": [], "dec_in": []}
    hooks = [b.register_forward_hook(lambda m, a, o: rec["out"].append(o)) for b in net.unet.input_blocks]
    hooks.append(net.unet.middle_block.register_forward_hook(lambda m, a, o: rec.__setitem__("mid", o)))
    hooks += [b.register_forward_pre_hook(lambda m, a: rec["dec_in"].append(a[0])) for b in net.unet.output_blocks]
    hooks += [b.register_forward_pre_hook(lambda m, a: rec.setdefault("enc_in", []).append(a[0]))
              for b in net.unet.input_blocks]
    return rec, hooks


@pytest.mark.parametrize("modulate_skips", [False, True])
def test_modulator_gates_forward_path_and_skips(modulate_skips):
    net = make("difareli", spatial_options={"modulate_skips": modulate_skips})
    x, s, ns = inputs("difareli")
    with torch.no_grad():
        m = net.spatial(s)
        cond = net.condition(s, ns)
        rec, hooks = _capture(net)
        net(x, torch.tensor([10, 20]), cond)
    for hk in hooks:
        hk.remove()
    n = len(net.unet.input_blocks)
    assert len(m) == n + 1 and all(mi.shape == oi.shape for mi, oi in zip(m, rec["out"] + [rec["mid"]]))
    for i in range(n - 1):  # o_i' = o_i * tanh(m_i) is the next encoder block's input
        torch.testing.assert_close(rec["enc_in"][i + 1], rec["out"][i] * torch.tanh(m[i]))
    # decoder: the first block gets [middle * tanh(m_mid), skip_{n-1}], then skips popped in reverse
    c_mid = rec["mid"].shape[1]
    torch.testing.assert_close(rec["dec_in"][0][:, :c_mid], rec["mid"] * torch.tanh(m[n]))
    for j, dec_in in enumerate(rec["dec_in"]):
        i = n - 1 - j
        skip = dec_in[:, dec_in.shape[1] - rec["out"][i].shape[1]:]
        want = rec["out"][i] * torch.tanh(m[i]) if modulate_skips else rec["out"][i]
        torch.testing.assert_close(skip, want)
        assert (skip - rec["out"][i]).abs().max() > 0 if modulate_skips else torch.equal(skip, rec["out"][i])


def test_zero_modulator_zeroes_first_half_forward_path_only():
    net = make("difareli++")
    with torch.no_grad():
        for p in net.spatial.parameters():
            p.zero_()
    x, s, ns = inputs("difareli++")
    with torch.no_grad():
        assert all(torch.equal(mi, torch.zeros_like(mi)) for mi in net.spatial(s))
        rec, hooks = _capture(net)
        eps = net(x, torch.tensor([5, 5]), net.condition(s, ns))
    for hk in hooks:
        hk.remove()
    assert all(o.abs().max() > 0 for o in rec["out"])  # the UNet's own outputs are not zero ...
    assert all(torch.equal(h, torch.zeros_like(h)) for h in rec["enc_in"][1:])  # ... but o*tanh(0) = 0 goes on
    assert torch.equal(rec["dec_in"][-1][:, -rec["out"][0].shape[1]:], rec["out"][0])  # skips unmodulated
    assert torch.isfinite(eps).all()


def test_modulator_runs_once_and_is_time_independent():
    net = make("difareli")
    x, s, ns = inputs("difareli")
    assert not any(isinstance(m, AdaGN) for m in net.spatial.modules())
    assert not any("time" in n for n, _ in net.spatial.named_parameters())
    with torch.no_grad():
        m1, m2 = net.spatial(s), net.spatial(s)
        assert all(torch.equal(a, b) for a, b in zip(m1, m2))
        cond = net.condition(s, ns)
        frozen = [g.clone() for g in cond.spatial]
        calls = []
        orig = net.spatial.forward
        net.spatial.forward = lambda *a, **k: calls.append(1) or orig(*a, **k)
        seen = {}
        orig_mod = net.spatial.modulate
        net.spatial.modulate = lambda lvl, h, st: (seen.setdefault(int(t_now[0]), []).append(st[lvl])
                                                   or orig_mod(lvl, h, st))
        outs = {}
        for t_now in (torch.tensor([3, 3]), torch.tensor([700, 700])):
            outs[int(t_now[0])] = net(x, t_now, cond)
    assert calls == []  # forward never re-runs the Modulator
    assert all(torch.equal(a, b) for a, b in zip(frozen, cond.spatial))
    assert all(a is b for a, b in zip(seen[3], seen[700]))  # the same gates at every t ...
    assert all(torch.equal(g, torch.tanh(m)) for g, m in zip(frozen, m1))
    assert (outs[3] - outs[700]).abs().max() > 1e-4  # ... while the UNet itself does depend on t


def test_gradients_reach_modulator_and_mlps():
    net = make("difareli").train()
    x, s, ns = inputs("difareli")
    loss = net(x, torch.tensor([1, 999]), net.condition(s, ns)).square().mean()
    loss.backward()
    mlp_params = [p for m in net.unet.modules() if isinstance(m, MLP3) for p in m.parameters()]
    assert len(mlp_params) == 6 * 11  # 11 residual blocks in tiny
    for p in list(net.spatial.parameters()) + mlp_params:
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().max() > 0


def test_state_dict_round_trip():
    net = make("difareli++")
    other = build_network("tiny", *DIFARELI_PP)
    missing = other.load_state_dict(net.state_dict())
    assert not missing.missing_keys and not missing.unexpected_keys
    assert any(k.startswith("spatial.input_blocks.") for k in net.state_dict())
    x, s, ns = inputs("difareli++")
    with torch.no_grad():
        assert torch.equal(net(x, torch.tensor([7, 8]), net.condition(s, ns)),
                           other.eval()(x, torch.tensor([7, 8]), other.condition(s, ns)))


def test_concat_spatial_is_concatenation_to_x_t():
    net = make("concat")
    assert isinstance(net.spatial, ConcatSpatial) and net.unet.input_blocks[0][0].in_channels == 6
    x, _, ns = inputs("concat")
    r = torch.randn(1, 3, 16, 16)  # one shading reference shared by the batch
    t = torch.tensor([100, 200])
    with torch.no_grad():
        got = net(x, t, net.condition(r, ns))
        want = net.unet(torch.cat([x, r.expand(2, -1, -1, -1)], dim=1), t, ns)
    assert torch.equal(got, want)


def test_timestep_forms_and_bind():
    net = make("difareli")
    x, s, ns = inputs("difareli")
    cond = net.condition(s, ns)
    with torch.no_grad():
        ref = net(x, torch.tensor([500, 500]), cond)
        assert torch.equal(net(x, 500, cond), ref)
        assert torch.equal(net(x, torch.tensor([500.0, 500.0]), cond), ref)
        assert torch.equal(net.bind(cond)(x, torch.tensor([500, 500])), ref)
        assert (net(x, torch.tensor([500.5, 500.5]), cond) - ref).abs().max() > 0


def test_condition_validation():
    net = make("difareli")
    _, s, ns = inputs("difareli")
    with pytest.raises(ValueError, match="spatial"):
        net.condition(None, ns)
    with pytest.raises(ValueError, match=r"\[B, 185\]"):
        net.condition(s, ns[:, :10])
    with pytest.raises(ValueError, match="no non-spatial"):
        make("unconditional").condition(None, ns)
    with pytest.raises(ValueError, match="timesteps"):
        net(torch.zeros(1, 3, 16, 16), torch.tensor([1, 2]), net.condition(s[:1], ns[:1]))
    with pytest.raises(KeyError, match="unknown spatial type 'hypernet'"):
        build_network("tiny", "hypernet", 6, 0)
    with pytest.raises(ValueError, match=r"no option\(s\) \['modulate_skip'\]"):
        build_network("tiny", {"type": "modulator", "modulate_skip": True}, 6, 0)
    with pytest.raises(ValueError, match="needs spatial inputs"):
        build_network("tiny", "concat", 0, 0)
    with pytest.raises(ValueError, match="model.spatial is null"):
        build_network("tiny", None, 6, 0)
    with pytest.raises(KeyError, match="unknown UNet option"):
        get_config("tiny", {"base_channel": 64})


def test_overrides_and_plain_config():
    cfg = get_config("ffhq128", {"channel_mult": (1, 2), "num_res_blocks": 1})
    assert isinstance(cfg, UNetConfig) and cfg.channel_mult == [1, 2] and cfg.attention_ds == {8, 16}
    assert cfg.to_dict()["base_channels"] == 128 and all(
        isinstance(v, (int, float, bool, list)) for v in cfg.to_dict().values())


def test_bf16_autocast_close_to_float32():
    net = make("difareli")
    x, s, ns = inputs("difareli", size=8)
    with torch.no_grad():
        ref = net(x, torch.tensor([50, 600]), net.condition(s, ns))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = net(x, torch.tensor([50, 600]), net.condition(s, ns))
    assert low.dtype == torch.bfloat16
    assert ((low.float() - ref).norm() / ref.norm()) < 0.05


def test_grad_checkpoint_matches():
    net = make("difareli").train()
    ck = make("difareli", overrides={"grad_checkpoint": True}).train()
    x, s, ns = inputs("difareli", b=1, size=8)
    for m in (net, ck):
        m(x, torch.tensor([3]), m.condition(s, ns)).square().sum().backward()
    for (n, a), b in zip(net.named_parameters(), ck.parameters()):
        torch.testing.assert_close(a.grad, b.grad, msg=n)


@pytest.mark.slow
def test_compile_fullgraph():
    net = make("difareli++")
    x, s, ns = inputs("difareli++")
    cond = net.condition(s, ns)
    with torch.no_grad():
        ref = net(x, torch.tensor([9, 9]), cond)
        net.compile(backend="aot_eager", fullgraph=True)
        torch.testing.assert_close(net(x, torch.tensor([9, 9]), cond), ref)


def test_modulator_standalone_levels_match_unet():
    cfg = get_config("tiny")
    mod = Modulator(cfg, DIFARELI_PP[1])
    shapes = [m.shape[1:] for m in mod(torch.zeros(1, DIFARELI_PP[1], 32, 32))]
    assert [s[0] for s in shapes] == build_network("tiny", *DIFARELI_PP).unet.encoder_channels
    assert [s[1] for s in shapes] == [32, 32, 16, 16, 8, 8, 8]


def test_resblock_updown_and_head_channels_variant():
    net = make("difareli", overrides={"resblock_updown": True, "num_head_channels": 16, "dropout": 0.1})
    attn = [m for m in net.unet.modules() if type(m).__name__ == "AttentionBlock"]
    assert attn and all(a.num_heads == a.qkv.in_channels // 16 for a in attn)
    assert sum(isinstance(m, ResBlock) for m in net.unet.modules()) == 11 + 2 + 2  # + 2 down + 2 up ResBlocks
    x, s, ns = inputs("difareli")
    with torch.no_grad():
        assert net(x, torch.tensor([1, 2]), net.condition(s, ns)).shape == x.shape


def test_spatial_registry_builds_from_the_unet_and_validates():
    from difareli.nn import SPATIAL_COMPONENTS, register_spatial
    from difareli.nn.unet import SpatialConditioning, TimestepBlock, UNet

    assert SPATIAL_COMPONENTS["modulator"] is Modulator and SPATIAL_COMPONENTS["concat"] is ConcatSpatial
    # The nested spec and the bare type name build the same network (same seed, same weights).
    torch.manual_seed(0)
    a = build_network("tiny", {"type": "modulator", "modulate_skips": True}, 6, 4)
    torch.manual_seed(0)
    b = build_network("tiny", "modulator", 6, 4)
    assert a.spatial.modulate_skips and not b.spatial.modulate_skips
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))

    seen = {}

    @register_spatial("_test_probe")
    class Probe(SpatialConditioning):
        """Adds 2 input channels and records the UNet it was built from."""

        @classmethod
        def extra_input_channels(cls, channels, **options):
            return 2

        @classmethod
        def build(cls, unet, channels, scale=1.0):
            seen.update(unet=unet, channels=channels, scale=scale)
            return cls()

        def validate(self, unet, image_channels):
            if unet.in_channels != image_channels + 2:
                raise ValueError("probe: wrong input width")

    try:
        net = build_network("tiny", {"type": "_test_probe", "scale": 3.0}, 5, 0)
        assert seen["unet"] is net.unet and isinstance(seen["unet"], UNet)  # the builder got the built UNet
        assert (seen["channels"], seen["scale"]) == (5, 3.0) and net.unet.in_channels == 5
        with pytest.raises(ValueError, match="already registered"):
            register_spatial("modulator")(Probe)
        # A component that does not fit the UNet is refused at construction.
        with pytest.raises(ValueError, match="do not match"):
            mod = Modulator(get_config("tiny", {"channel_mult": [1, 2]}), 6)
            mod.validate(net.unet, 3)
    finally:
        SPATIAL_COMPONENTS.pop("_test_probe")
    # UNet containers dispatch on the TimestepBlock marker, not on concrete classes.
    assert issubclass(ResBlock, TimestepBlock) and issubclass(AdaGN, TimestepBlock)
