"""The ADM UNet (Dhariwal & Nichol 2021) with DiFaReli's modified AdaGN and spatial-conditioning hooks (SPEC 4).

Layout (ADM, ``resblock_updown=False`` as in DiFaReli's public configs): an input conv, then per level
``num_res_blocks`` residual blocks (self-attention after each one at the configured resolutions) and a strided-conv
``Downsample`` between levels; a middle block (ResBlock, attention, ResBlock); a mirrored decoder whose blocks take
the matching encoder output through a skip connection; GroupNorm, SiLU and a zero-initialised output conv.

The "first half" (encoder) is built by :func:`build_encoder` so that the Modulator (``conditioning.py``) mirrors it
block for block with its own weights and no time input. Its per-level outputs are what spatial conditioning sees:
level ``i < len(input_blocks)`` is the output of input block ``i``, the last level is the middle block's output
(the public DiFaReli code modulates both).

Every residual block normalises with :class:`AdaGN`, ``k * (t_s * GN(h) + t_b)``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from difareli.errors import UserError

from .reuse import ReusedVector


@dataclass
class UNetConfig:
    """ADM hyper-parameters, plain values only (Hydra/checkpoint friendly).

    ``attention_resolutions`` are feature-map sizes (pixels) at ``image_size``; they are converted to downsampling
    factors, so a network built for 128 px still runs (with attention at the same depths) on smaller test images.
    """

    base_channels: int = 128
    channel_mult: list[int] = field(default_factory=lambda: [1, 1, 2, 3, 4])
    num_res_blocks: int = 2
    attention_resolutions: list[int] = field(default_factory=lambda: [16, 8])
    image_size: int = 128
    num_heads: int = 4
    num_head_channels: int = -1  # > 0 overrides num_heads with a fixed width per head
    dropout: float = 0.0
    resblock_updown: bool = False  # False: strided conv down / nearest+conv up (DiFaReli's setting)
    norm_groups: int = 32
    adagn_scale_plus_one: bool = True  # (1 + t_s) as in the public code; False: the paper's t_s
    adagn_hidden: int = 512  # hidden width of the per-block MLP3 (paper, Appendix III)
    # The public code ends MLP3 with a SiLU, the paper's Linear-SiLU-...-Linear does not; a side-by-side training
    # found no difference (conf/model/difareli_pp.yaml), so the public code's choice is the default.
    adagn_out_silu: bool = True
    grad_checkpoint: bool = False  # recompute residual/attention blocks in backward to save memory

    @property
    def attention_ds(self) -> set[int]:
        return {self.image_size // r for r in self.attention_resolutions}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class GroupNorm32(nn.GroupNorm):
    """GroupNorm computed in float32 and cast back (ADM's choice: bf16/fp16 statistics are unstable).

    On a CPU a contiguous bfloat16 input goes to PyTorch's mixed-type kernel (bf16 activations, fp32 affine), which
    computes the statistics and the affine in float32 internally and rounds the output once: the same arithmetic as the
    explicit cast, without writing an fp32 copy of the activation forward and backward (the casts were ~18% of a
    tiny-64 bf16 training step; the mixed kernel's forward + backward is ~3x faster than cast, norm, cast back).
    """

    def forward(self, x: Tensor) -> Tensor:
        # Contiguous (NCHW) only: on channels-last input (the inference copy's layout) the mixed kernel took 350-500 us
        # per call at 16 x 16 px against ~30 for the cast path (batch 12: 5 ms against 0.6; issue 63).
        if (x.dtype == torch.bfloat16 and x.device.type == "cpu" and self.weight.dtype == torch.float32
                and x.is_contiguous()):
            return F.group_norm(x, self.num_groups, self.weight, self.bias, self.eps)
        return F.group_norm(x.float(), self.num_groups, self.weight, self.bias, self.eps).to(x.dtype)


def timestep_embedding(t: Tensor, dim: int, max_period: float = 10000.0) -> Tensor:
    """Sinusoidal embedding gamma(t) of (possibly fractional) timesteps, [B] -> [B, dim], ADM's cos-then-sin order."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
    return emb


def zero_module(module: nn.Module) -> nn.Module:
    """Zero a module's parameters (ADM initialises residual outputs to zero so each block starts as identity)."""
    for p in module.parameters():
        nn.init.zeros_(p)
    return module


class MLP3(nn.Sequential):
    """The per-block non-spatial MLP: Linear-SiLU-Linear-SiLU-Linear (hidden 512) giving k in R^C."""

    def __init__(self, in_dim: int, hidden: int, out_dim: int, out_silu: bool = False):
        layers: list[nn.Module] = [nn.Linear(in_dim, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(),
                                   nn.Linear(hidden, out_dim)]
        if out_silu:
            layers.append(nn.SiLU())
        super().__init__(*layers)


class TimestepBlock(nn.Module):
    """Marker interface (guided-diffusion's ``TimestepBlock``): ``forward(h, emb, nonspatial)`` takes the time
    embedding and the non-spatial vector. Containers dispatch on this marker, never on concrete classes, so a new
    conditioned layer (e.g. cross-attention) only subclasses it."""

    def forward(self, h: Tensor, emb: Tensor | None = None, nonspatial: Tensor | None = None) -> Tensor:
        raise NotImplementedError


class AdaGN(TimestepBlock):
    """Modified adaptive GroupNorm, ``AdaGN(h) = k * (t_s * GN(h) + t_b)`` (paper Eq. AdaGN, SPEC 4).

    ``(t_s, t_b) = Linear(SiLU(emb))`` from the time embedding; ``k = MLP3(nonspatial)`` when ``nonspatial_dim > 0``,
    otherwise ``k = 1``. ``scale_plus_one`` uses ``1 + t_s`` (public code) so a zero time projection is identity.
    """

    def __init__(self, channels: int, emb_dim: int, nonspatial_dim: int = 0, *, groups: int = 32,
                 scale_plus_one: bool = True, hidden: int = 512, out_silu: bool = False):
        super().__init__()
        self.norm = GroupNorm32(groups, channels)
        self.time = nn.Sequential(nn.SiLU(), nn.Linear(emb_dim, 2 * channels))
        self.mlp = MLP3(nonspatial_dim, hidden, channels, out_silu) if nonspatial_dim > 0 else None
        self.scale_plus_one = scale_plus_one

    def forward(self, h: Tensor, emb: Tensor, nonspatial: Tensor | None = None) -> Tensor:
        t_s, t_b = self.time(emb)[..., None, None].chunk(2, dim=1)
        if self.scale_plus_one:
            t_s = 1 + t_s
        out = t_s * self.norm(h) + t_b
        if self.mlp is not None:
            if nonspatial is None:
                raise UserError("this network has non-spatial (AdaGN MLP3) conditioning; pass a non-spatial vector")
            k = nonspatial.scale(self) if isinstance(nonspatial, ReusedVector) else self.mlp(nonspatial)
            out = out * k[..., None, None]
        return out


class ResBlock(TimestepBlock):
    """ADM residual block. ``emb_dim > 0``: AdaGN before the second conv; ``emb_dim == 0`` (Modulator): plain GN."""

    def __init__(self, channels: int, out_channels: int, emb_dim: int, nonspatial_dim: int, cfg: UNetConfig,
                 up: bool = False, down: bool = False):
        super().__init__()
        g = cfg.norm_groups
        self.in_norm = GroupNorm32(g, channels)
        self.in_conv = nn.Conv2d(channels, out_channels, 3, padding=1)
        self.resample = Resample(up, down)
        if emb_dim > 0:
            self.out_norm: nn.Module = AdaGN(out_channels, emb_dim, nonspatial_dim, groups=g,
                                             scale_plus_one=cfg.adagn_scale_plus_one, hidden=cfg.adagn_hidden,
                                             out_silu=cfg.adagn_out_silu)
        else:
            self.out_norm = GroupNorm32(g, out_channels)
        self.dropout = nn.Dropout(cfg.dropout)
        self.out_conv = zero_module(nn.Conv2d(out_channels, out_channels, 3, padding=1))
        self.skip = nn.Identity() if out_channels == channels else nn.Conv2d(channels, out_channels, 1)
        self.grad_checkpoint = cfg.grad_checkpoint

    def forward(self, x: Tensor, emb: Tensor | None = None, nonspatial: Tensor | None = None) -> Tensor:
        if self.grad_checkpoint and torch.is_grad_enabled():
            return checkpoint(self._forward, x, emb, nonspatial, use_reentrant=False)
        return self._forward(x, emb, nonspatial)

    def _forward(self, x: Tensor, emb: Tensor | None, nonspatial: Tensor | None) -> Tensor:
        h = F.silu(self.in_norm(x))
        # up/down-sample after the activation and before the conv, and the skip path alike (ADM)
        h, x = self.resample(h), self.resample(x)
        h = self.in_conv(h)
        h = self.out_norm(h, emb, nonspatial) if isinstance(self.out_norm, TimestepBlock) else self.out_norm(h)
        h = self.out_conv(self.dropout(F.silu(h)))
        return self.skip(x) + h


class Resample(nn.Module):
    """Parameter-free nearest upsampling / average-pool downsampling used inside up/down ResBlocks."""

    def __init__(self, up: bool = False, down: bool = False):
        super().__init__()
        self.mode = "up" if up else "down" if down else None

    def forward(self, x: Tensor) -> Tensor:
        if self.mode == "up":
            return F.interpolate(x, scale_factor=2, mode="nearest")
        if self.mode == "down":
            return F.avg_pool2d(x, 2)
        return x


class Downsample(nn.Module):
    """Strided 3x3 conv halving the resolution (ADM ``conv_resample=True``)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, stride=2, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(x)


class Upsample(nn.Module):
    """Nearest x2 upsampling followed by a 3x3 conv (ADM ``conv_resample=True``)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(F.interpolate(x, scale_factor=2, mode="nearest"))


class AttentionBlock(nn.Module):
    """Spatial self-attention with a residual, zero-initialised output projection (ADM, "new" q/k/v order)."""

    def __init__(self, channels: int, cfg: UNetConfig):
        super().__init__()
        if cfg.num_head_channels > 0:
            if channels % cfg.num_head_channels:
                raise UserError(f"{channels} channels not divisible by num_head_channels={cfg.num_head_channels}")
            self.num_heads = channels // cfg.num_head_channels
        else:
            self.num_heads = cfg.num_heads
        if channels % self.num_heads:
            raise UserError(f"{channels} channels not divisible by num_heads={self.num_heads}")
        self.norm = GroupNorm32(cfg.norm_groups, channels)
        self.qkv = nn.Conv1d(channels, 3 * channels, 1)
        self.proj_out = zero_module(nn.Conv1d(channels, channels, 1))
        self.grad_checkpoint = cfg.grad_checkpoint

    def forward(self, x: Tensor) -> Tensor:
        if self.grad_checkpoint and torch.is_grad_enabled():
            return checkpoint(self._forward, x, use_reentrant=False)
        return self._forward(x)

    def _forward(self, x: Tensor) -> Tensor:
        b, c, hh, ww = x.shape
        flat = x.reshape(b, c, hh * ww)
        q, k, v = self.qkv(self.norm(flat)).reshape(b, 3, self.num_heads, c // self.num_heads, hh * ww).unbind(1)
        # SDPA wants [B, heads, T, d]; it picks a fused kernel on GPU and handles bf16 softmax internally
        a = F.scaled_dot_product_attention(q.transpose(-1, -2), k.transpose(-1, -2), v.transpose(-1, -2))
        h = self.proj_out(a.transpose(-1, -2).reshape(b, c, hh * ww))
        return (flat + h).reshape(b, c, hh, ww)


class Block(nn.ModuleList):
    """A sequence of layers; :class:`TimestepBlock` layers (residual blocks) also receive the time embedding and
    the non-spatial vector."""

    def forward(self, h: Tensor, emb: Tensor | None = None,  # type: ignore[override]
                nonspatial: Tensor | None = None) -> Tensor:
        for layer in self:
            h = layer(h, emb, nonspatial) if isinstance(layer, TimestepBlock) else layer(h)
        return h


#: Builds the layer a non-spatial component adds after every residual block (e.g. cross-attention), by width.
LayerFactory = Callable[[int], nn.Module]


def attention_layers(ch: int, cfg: UNetConfig, ds: int, cross_attention: LayerFactory | None = None
                     ) -> list[nn.Module]:
    """Self-attention at the configured resolutions, then (if given) a non-spatial layer at every resolution."""
    layers: list[nn.Module] = [AttentionBlock(ch, cfg)] if ds in cfg.attention_ds else []
    if cross_attention is not None:
        layers.append(cross_attention(ch))
    return layers


def build_encoder(cfg: UNetConfig, in_channels: int, emb_dim: int, nonspatial_dim: int,
                  cross_attention: LayerFactory | None = None) -> tuple[nn.ModuleList, Block, list[int]]:
    """The UNet's first half: ``(input_blocks, middle_block, skip_channels)``.

    ``emb_dim = 0`` builds the time-free variant (plain GroupNorm) used by the Modulator; the layout is otherwise
    identical, so its per-level outputs match the UNet's shape for shape. ``cross_attention`` adds a
    non-spatial layer (a :class:`TimestepBlock`) after every residual block (``nn/nonspatial.py``).
    """
    ch = cfg.base_channels * cfg.channel_mult[0]
    blocks = nn.ModuleList([Block([nn.Conv2d(in_channels, ch, 3, padding=1)])])
    skip_channels = [ch]
    ds = 1
    for level, mult in enumerate(cfg.channel_mult):
        for _ in range(cfg.num_res_blocks):
            out = cfg.base_channels * mult
            layers: list[nn.Module] = [ResBlock(ch, out, emb_dim, nonspatial_dim, cfg)]
            ch = out
            layers += attention_layers(ch, cfg, ds, cross_attention)
            blocks.append(Block(layers))
            skip_channels.append(ch)
        if level != len(cfg.channel_mult) - 1:
            down = ResBlock(ch, ch, emb_dim, nonspatial_dim, cfg, down=True) if cfg.resblock_updown else Downsample(ch)
            blocks.append(Block([down]))
            skip_channels.append(ch)
            ds *= 2
    middle_attention = [AttentionBlock(ch, cfg)] + ([cross_attention(ch)] if cross_attention is not None else [])
    middle = Block([ResBlock(ch, ch, emb_dim, nonspatial_dim, cfg), *middle_attention,
                    ResBlock(ch, ch, emb_dim, nonspatial_dim, cfg)])
    return blocks, middle, skip_channels


class SpatialConditioning(nn.Module):
    """Hooks through which spatial conditioning enters the UNet; this base class is the identity (no spatial input).

    A component is prepared once per condition (``prepare``, no ``t``), then at every denoising step the UNet calls
    ``step`` (per-step work that needs ``x_t``/``t``, e.g. a ControlNet encoder; identity here), ``apply_input``
    (e.g. concatenate to ``x_t``) and, after every encoder level, ``modulate`` which returns the tensors for the
    forward path and for the skip connection (the Modulator multiplies, a ControlNet would add to the skip).

    Construction (``conditioning.py`` registers components by config ``type``): ``extra_input_channels`` says how
    many channels ``apply_input`` adds to ``x_t`` *before* the UNet exists (its input conv depends on it); then
    ``build(unet, channels, **options)`` receives the built UNet (a ControlNet copies its encoder) and
    ``validate(unet, image_channels)`` checks the component against it.
    """

    needs_input: bool = False
    #: the config ``type`` this class is registered under (set by ``conditioning.register_spatial``)
    type_name: str = ""

    @classmethod
    def extra_input_channels(cls, channels: int, **options: Any) -> int:
        """Channels ``apply_input`` adds to ``x_t`` for a spatial input of ``channels`` channels."""
        return 0

    @classmethod
    def build(cls, unet: UNet, channels: int, **options: Any) -> SpatialConditioning:
        """The component for ``unet`` and a spatial input of ``channels`` channels."""
        raise NotImplementedError(f"{cls.__name__} does not define build(unet, channels, **options)")

    def validate(self, unet: UNet, image_channels: int) -> None:
        """Raise ``ValueError`` if this component does not fit ``unet`` (levels, widths, input channels)."""

    def prepare(self, spatial: Tensor | None) -> Any:
        return None

    def step(self, x: Tensor, emb: Tensor, nonspatial: Tensor | None, state: Any) -> Any:
        return state

    def apply_input(self, x: Tensor, state: Any) -> Tensor:
        return x

    def modulate(self, level: int, h: Tensor, state: Any) -> tuple[Tensor, Tensor]:
        return h, h


_NO_SPATIAL = SpatialConditioning()


class UNet(nn.Module):
    """ADM UNet predicting eps, with AdaGN (time + optional non-spatial k) in every residual block."""

    def __init__(self, cfg: UNetConfig, in_channels: int = 3, out_channels: int = 3, nonspatial_dim: int = 0,
                 cross_attention: LayerFactory | None = None):
        super().__init__()
        self.cfg, self.nonspatial_dim, self.in_channels = cfg, nonspatial_dim, in_channels
        # kept so that a ControlNet copying the encoder builds the same non-spatial layers
        self.cross_attention = cross_attention
        base = cfg.base_channels
        emb_dim = 4 * base
        self.time_embed = nn.Sequential(nn.Linear(base, emb_dim), nn.SiLU(), nn.Linear(emb_dim, emb_dim))
        self.input_blocks, self.middle_block, skip_channels = build_encoder(cfg, in_channels, emb_dim, nonspatial_dim,
                                                                           cross_attention)
        self.encoder_channels = list(skip_channels) + [skip_channels[-1]]  # per modulation level (+ middle)
        ch = skip_channels[-1]
        ds = 2 ** (len(cfg.channel_mult) - 1)
        self.output_blocks = nn.ModuleList()
        for level, mult in reversed(list(enumerate(cfg.channel_mult))):
            for i in range(cfg.num_res_blocks + 1):
                out = base * mult
                layers: list[nn.Module] = [ResBlock(ch + skip_channels.pop(), out, emb_dim, nonspatial_dim, cfg)]
                ch = out
                layers += attention_layers(ch, cfg, ds, cross_attention)
                if level and i == cfg.num_res_blocks:
                    layers.append(ResBlock(ch, ch, emb_dim, nonspatial_dim, cfg, up=True) if cfg.resblock_updown
                                  else Upsample(ch))
                    ds //= 2
                self.output_blocks.append(Block(layers))
        self.out = nn.Sequential(GroupNorm32(cfg.norm_groups, ch), nn.SiLU(),
                                 zero_module(nn.Conv2d(ch, out_channels, 3, padding=1)))

    @property
    def num_levels(self) -> int:
        """Number of encoder levels a spatial component sees: every input block plus the middle block."""
        return len(self.input_blocks) + 1

    def forward(self, x: Tensor, t: Tensor, nonspatial: Tensor | None = None,
                spatial: SpatialConditioning | None = None, state: Any = None) -> Tensor:
        """eps for ``x`` at timesteps ``t`` ([B], int or float), with optional conditioning hooks and their state."""
        spatial = _NO_SPATIAL if spatial is None else spatial
        emb = self.time_embed(timestep_embedding(t, self.cfg.base_channels))
        state = spatial.step(x, emb, nonspatial, state)
        h = spatial.apply_input(x, state)
        skips = []
        for level, block in enumerate(self.input_blocks):
            h, skip = spatial.modulate(level, block(h, emb, nonspatial), state)
            skips.append(skip)
        h, _ = spatial.modulate(len(self.input_blocks), self.middle_block(h, emb, nonspatial), state)
        for block in self.output_blocks:
            h = block(torch.cat([h, skips.pop()], dim=1), emb, nonspatial)
        return self.out(h)
