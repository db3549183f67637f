"""Non-spatial conditioning components: how the non-spatial vector (shape, cam, identity, c, ...) enters the UNet.

A model config names one as ``nonspatial: {type: adagn | crossattn, <options>}`` (``conf/model/nonspatial/``):

- :class:`AdaGNNonSpatial` (DiFaReli, DiFaReli++; the default, so older checkpoints load unchanged): the vector
  goes to every residual block, where AdaGN's MLP3 turns it into the scale ``k`` (``unet.AdaGN``).
- :class:`CrossAttentionNonSpatial` (Table IV "CA" rows, as Stable Diffusion + ControlNet condition on text):
  :class:`ContextTokens` turns the vector into context tokens (``tokens_per_input`` per encoding, projected to
  ``context_dim``, plus a learned embedding per token saying which encoding it came from), and a
  :class:`CrossAttentionBlock` after every residual block attends to them. The UNet's self-attention exists only
  at ``attention_resolutions``; the cross-attention layer is added at *every* resolution, so that the vector
  reaches every level as AdaGN's does (SD places a cross-attention transformer at each attention level; here every
  level has one). AdaGN keeps its time path and loses its MLP3 (``k = 1``).

Both run their t-independent part once per condition (``prepare``); the blocks receive its result as their
``nonspatial`` argument and dispatch on the :class:`~difareli.nn.unet.TimestepBlock` marker.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from difareli.errors import UserError

from .unet import GroupNorm32, LayerFactory, TimestepBlock, UNetConfig, zero_module

NONSPATIAL_COMPONENTS: dict[str, type[NonSpatialConditioning]] = {}


def register_nonspatial(name: str):
    """Class decorator: make a component available as ``nonspatial: {type: name}``."""

    def register(cls):
        NONSPATIAL_COMPONENTS[name] = cls
        cls.type_name = name
        return cls

    return register


class NonSpatialConditioning(nn.Module):
    """Base: the width AdaGN's MLP3s take (``adagn_dim``), the layer added after every residual block
    (``block_layer``) and ``prepare(vector)`` -> what the blocks receive as ``nonspatial``."""

    type_name = ""
    reusable = False  # what the blocks receive may be wrapped for reuse across steps (reuse.ReusedVector)

    def __init__(self, widths: Sequence[int], *, cfg: UNetConfig):
        super().__init__()
        self.widths = [int(w) for w in widths]

    @property
    def adagn_dim(self) -> int:
        return 0

    def block_layer(self, cfg: UNetConfig) -> LayerFactory | None:
        return None

    def prepare(self, vector: Tensor | None) -> Tensor | None:
        return vector


@register_nonspatial("adagn")
class AdaGNNonSpatial(NonSpatialConditioning):
    """DiFaReli's AdaGN: the (normalised) vector itself reaches every residual block's MLP3; no parameters here."""

    reusable = True

    @property
    def adagn_dim(self) -> int:
        return sum(self.widths)


class ContextTokens(nn.Module):
    """Non-spatial vector [B, sum(widths)] -> context tokens [B, len(widths) * tokens_per_input, context_dim].

    Each encoding has its own linear projection; a learned per-token embedding tells tokens apart, so the context
    is ordered (permutation-aware) although attention itself treats its keys as a set.
    """

    def __init__(self, widths: Sequence[int], context_dim: int, tokens_per_input: int = 1):
        super().__init__()
        self.widths, self.context_dim, self.per_input = list(widths), int(context_dim), int(tokens_per_input)
        self.proj = nn.ModuleList(nn.Linear(w, self.per_input * self.context_dim) for w in self.widths)
        self.token_embedding = nn.Parameter(torch.randn(len(self.widths) * self.per_input, self.context_dim) * 0.02)
        self.norm = nn.LayerNorm(self.context_dim)

    def forward(self, vector: Tensor) -> Tensor:
        if vector.ndim != 2 or vector.shape[1] != sum(self.widths):
            raise UserError(f"expected a non-spatial vector [B, {sum(self.widths)}], got {tuple(vector.shape)}")
        parts = vector.split(self.widths, dim=1)
        tokens = torch.cat([p(x).view(x.shape[0], self.per_input, self.context_dim)
                            for p, x in zip(self.proj, parts)], dim=1)
        return self.norm(tokens + self.token_embedding)


class CrossAttentionBlock(TimestepBlock):
    """``h + proj_out(attn(q = GN(h), k, v = context))``: image positions attend to the context tokens.

    The output projection starts at zero (as ADM's and SD's attention outputs), so at initialisation the block is
    the identity. It reads the context from the ``nonspatial`` argument of the TimestepBlock interface.
    """

    def __init__(self, channels: int, context_dim: int, num_heads: int, groups: int = 32):
        super().__init__()
        if channels % num_heads:
            raise UserError(f"{channels} channels not divisible by {num_heads} cross-attention heads")
        self.num_heads = num_heads
        self.norm = GroupNorm32(groups, channels)
        self.q = nn.Conv1d(channels, channels, 1)
        self.kv = nn.Linear(context_dim, 2 * channels)
        self.proj_out = zero_module(nn.Conv1d(channels, channels, 1))

    def forward(self, h: Tensor, emb: Tensor | None = None, nonspatial: Tensor | None = None) -> Tensor:
        if nonspatial is None or nonspatial.ndim != 3:
            got = None if nonspatial is None else tuple(nonspatial.shape)
            raise UserError(f"cross-attention needs context tokens [B, N, C], got {got}")
        b, c, hh, ww = h.shape
        flat = h.reshape(b, c, hh * ww)
        ctx = nonspatial.to(h.dtype)
        if ctx.shape[0] != b:  # one condition shared by a batch of x_t
            ctx = ctx.expand(b, -1, -1)
        d = c // self.num_heads
        q = self.q(self.norm(flat)).reshape(b, self.num_heads, d, hh * ww).transpose(-1, -2)
        k, v = self.kv(ctx).reshape(b, -1, 2, self.num_heads, d).permute(2, 0, 3, 1, 4).unbind(0)
        a = F.scaled_dot_product_attention(q, k, v)  # [B, heads, HW, d]
        return (flat + self.proj_out(a.transpose(-1, -2).reshape(b, c, hh * ww))).reshape(b, c, hh, ww)


@register_nonspatial("crossattn")
class CrossAttentionNonSpatial(NonSpatialConditioning):
    """Context tokens + a cross-attention layer after every residual block (replaces AdaGN's MLP3 path).

    ``context_dim`` null: the UNet's time-embedding width (4 x base channels); ``num_heads`` null: the preset's.
    """

    def __init__(self, widths: Sequence[int], context_dim: int | None = None, tokens_per_input: int = 1,
                 num_heads: int | None = None, *, cfg: UNetConfig):
        super().__init__(widths, cfg=cfg)
        self.context_dim = int(context_dim) if context_dim else 4 * cfg.base_channels
        self.num_heads = int(num_heads) if num_heads else cfg.num_heads
        if int(tokens_per_input) < 1:
            raise UserError(f"nonspatial.tokens_per_input must be >= 1, got {tokens_per_input}")
        self.tokens = ContextTokens(self.widths, self.context_dim, tokens_per_input) if self.widths else None

    def block_layer(self, cfg: UNetConfig) -> LayerFactory | None:
        if self.tokens is None:  # no non-spatial inputs: nothing to attend to
            return None
        return functools.partial(CrossAttentionBlock, context_dim=self.context_dim, num_heads=self.num_heads,
                                 groups=cfg.norm_groups)

    def prepare(self, vector: Tensor | None) -> Tensor | None:
        return None if vector is None or self.tokens is None else self.tokens(vector)


def build_nonspatial(spec: str | Mapping[str, Any] | None, widths: Sequence[int], cfg: UNetConfig
                     ) -> NonSpatialConditioning:
    """The component for a spec (``None``/``"adagn"``, a type name, or ``{type: ..., <options>}``)."""
    options = {"type": spec or "adagn"} if not isinstance(spec, Mapping) else dict(spec)
    kind = options.pop("type", None) or "adagn"
    if kind not in NONSPATIAL_COMPONENTS:
        raise UserError(f"unknown model.nonspatial.type {kind!r}; known: {sorted(NONSPATIAL_COMPONENTS)}")
    try:
        return NONSPATIAL_COMPONENTS[kind](widths, cfg=cfg, **options)
    except TypeError as e:  # an unknown option: name it
        raise UserError(f"model.nonspatial ({kind}): {e}") from None
