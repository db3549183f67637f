"""DiffusionNet: the UNet composed with its spatial and non-spatial conditioning (docs/architecture.md, Network).

``cond = net.condition(spatial, nonspatial)`` runs everything that does not depend on ``t`` or ``x_t`` once per
condition (the Modulator); ``net(x_t, t, cond)`` then predicts eps at every step. :func:`build_network` builds one
from plain values (preset name, spatial spec, channel counts), which is what Hydra configs and checkpoints store.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from difareli.errors import UserError

from . import controlnet  # noqa: F401  (registers spatial type "controlnet")
from .conditioning import count_parameters, resolve_spatial
from .nonspatial import CrossAttentionBlock, build_nonspatial
from .presets import get_config
from . import reuse
from .unet import MLP3, UNet, UNetConfig


@dataclass
class Condition:
    """A prepared condition: the spatial component's state (e.g. the Modulator's tanh(m_i), a ControlNet's hint
    features) and what the non-spatial component hands the blocks (AdaGN: the vector [B, D], its MLP3s run inside
    the blocks; cross-attention: context tokens [B, N, C]). Independent of ``t`` and ``x_t``."""

    spatial: Any = None
    nonspatial: Tensor | None = None

    def reused(self) -> reuse.ReusedVector:
        """The non-spatial vector as every step this condition serves receives it (``reuse.ReusedVector``: AdaGN's
        k computed once); kept on the condition, outside its fields, so a copied condition starts afresh."""
        r = self.__dict__.get("_reused")
        if r is None or r.vector is not self.nonspatial:
            r = self.__dict__["_reused"] = reuse.ReusedVector(self.nonspatial)
        return r


class DiffusionNet(nn.Module):
    """eps-prediction network: :class:`UNet` + optional spatial component + non-spatial component.

    ``spatial`` is a spec (``None``, a registered type name, or ``{type: ..., <options>}``); the component is built
    from the UNet (``SpatialConditioning.build``) and validates itself against it. ``nonspatial`` likewise names
    the non-spatial component (``nn/nonspatial.py``; default AdaGN); ``nonspatial_widths`` are the widths of the
    encodings making up the vector (cross-attention makes tokens per encoding; default: one block).
    """

    def __init__(self, config: UNetConfig, spatial: str | Mapping[str, Any] | None = None, spatial_channels: int = 0,
                 nonspatial_dim: int = 0, image_channels: int = 3, nonspatial: str | Mapping[str, Any] | None = None,
                 nonspatial_widths: list[int] | None = None):
        super().__init__()
        self.config, self.nonspatial_dim, self.image_channels = config, nonspatial_dim, image_channels
        widths = list(nonspatial_widths) if nonspatial_widths else ([nonspatial_dim] if nonspatial_dim else [])
        if sum(widths) != nonspatial_dim:
            raise UserError(f"non-spatial widths {widths} do not add up to nonspatial_dim={nonspatial_dim}")
        self.nonspatial = build_nonspatial(nonspatial, widths, config)
        component, options = resolve_spatial(spatial, spatial_channels)
        extra = component.extra_input_channels(spatial_channels, **options) if component is not None else 0
        self.unet = UNet(config, in_channels=image_channels + extra, out_channels=image_channels,
                         nonspatial_dim=self.nonspatial.adagn_dim, cross_attention=self.nonspatial.block_layer(config))
        self.spatial = component.build(self.unet, spatial_channels, **options) if component is not None else None
        if self.spatial is not None:
            self.spatial.validate(self.unet, image_channels)

    def condition(self, spatial: Tensor | None = None, nonspatial: Tensor | None = None) -> Condition:
        """Prepare a condition once (the Modulator, a ControlNet's hint encoder, the context tokens); reuse it for
        every timestep."""
        if self.nonspatial_dim > 0:
            if nonspatial is None or nonspatial.ndim != 2 or nonspatial.shape[1] != self.nonspatial_dim:
                got = None if nonspatial is None else tuple(nonspatial.shape)
                raise UserError(f"expected a non-spatial vector [B, {self.nonspatial_dim}], got {got}")
        elif nonspatial is not None:
            raise UserError("this network has no non-spatial conditioning (nonspatial_dim=0) but got a vector")
        if self.spatial is None:
            if spatial is not None:
                raise UserError("this network has no spatial conditioning but got a spatial input")
            state = None
        else:
            state = self.spatial.prepare(spatial)
        return Condition(spatial=state, nonspatial=self.nonspatial.prepare(nonspatial))

    def forward(self, x_t: Tensor, t: Tensor | float | int, cond: Condition | None = None) -> Tensor:
        """eps for ``x_t`` [B, C, H, W] at ``t`` ([B] long in 0..T-1 or float; a scalar is broadcast)."""
        if not torch.is_tensor(t) or t.ndim == 0:
            t = torch.as_tensor(t, device=x_t.device).expand(x_t.shape[0])
        if t.shape != (x_t.shape[0],):
            raise UserError(f"expected timesteps [{x_t.shape[0]}] for x_t {tuple(x_t.shape)}, got {tuple(t.shape)}")
        cond = cond if cond is not None else self.condition()
        ns = cond.nonspatial
        if ns is not None and self.nonspatial.reusable and reuse.allowed():
            ns = cond.reused()
        return self.unet(x_t, t, ns, self.spatial, cond.spatial)

    def bind(self, cond: Condition) -> Callable[[Tensor, Tensor], Tensor]:
        """The sampler-facing denoiser ``(x, t) -> eps`` for one prepared condition."""
        return lambda x, t: self(x, t, cond)

    def parameter_counts(self) -> dict[str, int]:
        """Parameters of the UNet proper, the spatial component (a ControlNet's own MLP3s / cross-attention
        included), the UNet's AdaGN MLP3s, its cross-attention (with the context tokens), and in total."""
        mlps = sum(count_parameters(m) for m in self.unet.modules() if isinstance(m, MLP3))
        crossattn = count_parameters(self.nonspatial) + sum(
            count_parameters(m) for m in self.unet.modules() if isinstance(m, CrossAttentionBlock))
        spatial = count_parameters(self.spatial)
        total = count_parameters(self)
        return {"unet": total - spatial - mlps - crossattn, "spatial": spatial, "mlps": mlps, "crossattn": crossattn,
                "total": total}


def build_network(preset: str = "tiny", spatial: str | Mapping[str, Any] | None = "modulator",
                  spatial_channels: int = 0, nonspatial_dim: int = 0, image_channels: int = 3,
                  overrides: dict[str, Any] | None = None, nonspatial: str | Mapping[str, Any] | None = None,
                  nonspatial_widths: list[int] | None = None) -> DiffusionNet:
    """Build a :class:`DiffusionNet` from plain values.

    ``spatial``: ``None``, a registered component type (``"modulator"``: DiFaReli/++, ``"concat"``: ablation (a))
    or ``{"type": ..., <options>}`` (e.g. ``{"type": "modulator", "modulate_skips": True}``);
    ``overrides``: :class:`UNetConfig` fields replacing the preset's; ``nonspatial``: ``None``/``"adagn"`` or
    ``{"type": "crossattn", ...}`` with the encodings' ``nonspatial_widths``.
    """
    cfg = get_config(preset, overrides)
    return DiffusionNet(cfg, spatial, spatial_channels, nonspatial_dim=nonspatial_dim, image_channels=image_channels,
                        nonspatial=nonspatial, nonspatial_widths=nonspatial_widths)
