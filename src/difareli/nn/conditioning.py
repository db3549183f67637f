"""Spatial-conditioning components plugged into the UNet's hooks (SPEC 4, ablations SPEC 9).

A component subclasses :class:`~difareli.nn.unet.SpatialConditioning`: ``prepare(spatial)`` runs once per condition
and returns a state; the UNet then calls ``step`` / ``apply_input`` / ``modulate(level, h, state)`` at every step.
Variants are new components, never UNet edits:

- :class:`Modulator` (DiFaReli, DiFaReli++): a time-free copy of the UNet's first half; ``o_i' = o_i * tanh(m_i)``.
- :class:`ConcatSpatial` (ablation (a), "no Modulator"): the spatial input concatenated to ``x_t`` at every step.
- A ControlNet (ablation, later) fits as: ``step`` runs its time-conditioned encoder copy on ``x_t`` plus the hint
  and returns per-level residuals; ``modulate`` returns ``(h, h + residual)`` for input levels (skip path) and
  ``(h + residual, h)`` for the middle level. Cross-attention non-spatial conditioning would instead give the
  UNet's attention blocks a context; it is independent of these hooks.

Non-spatial AdaGN conditioning (the per-block MLP3s) lives in the UNet's residual blocks (``unet.AdaGN``).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from .unet import SpatialConditioning, UNetConfig, build_encoder

__all__ = ["SPATIAL_COMPONENTS", "ConcatSpatial", "Modulator", "SpatialConditioning", "build_spatial"]


def _check_spatial(name: str, spatial: Tensor | None, channels: int) -> Tensor:
    if spatial is None:
        raise ValueError(f"{name} needs a spatial input with {channels} channels, got None")
    if spatial.ndim != 4 or spatial.shape[1] != channels:
        raise ValueError(f"{name} expects spatial [B, {channels}, H, W], got {tuple(spatial.shape)}")
    return spatial


class Modulator(SpatialConditioning):
    """DiFaReli's Modulator: the UNet's first half (input conv, input blocks, middle block), separate weights, no t.

    Its output at level ``i`` (``m_i``, same shape as the UNet's ``o_i``) gates the UNet's forward path,
    ``o_i' = o_i * tanh(m_i)``. By default the skip connection keeps the unmodulated ``o_i`` (public code);
    ``modulate_skips=True`` sends ``o_i'`` to the decoder too. The state holds ``tanh(m_i)``, computed once.
    """

    needs_input = True

    def __init__(self, cfg: UNetConfig, in_channels: int, modulate_skips: bool = False):
        super().__init__()
        self.in_channels, self.modulate_skips = in_channels, modulate_skips
        self.input_blocks, self.middle_block, _ = build_encoder(cfg, in_channels, emb_dim=0, nonspatial_dim=0)

    @property
    def num_levels(self) -> int:
        return len(self.input_blocks) + 1

    def forward(self, spatial: Tensor) -> list[Tensor]:
        """The raw per-level outputs ``m_i`` (before tanh)."""
        h = _check_spatial("Modulator", spatial, self.in_channels)
        outs = []
        for block in self.input_blocks:
            h = block(h)
            outs.append(h)
        outs.append(self.middle_block(h))
        return outs

    def prepare(self, spatial: Tensor | None) -> list[Tensor]:
        return [m.tanh() for m in self(spatial)]

    def modulate(self, level: int, h: Tensor, state: list[Tensor]) -> tuple[Tensor, Tensor]:
        gated = h * state[level]
        return gated, (gated if self.modulate_skips else h)


class ConcatSpatial(SpatialConditioning):
    """Ablation (a): the spatial input (e.g. the shading reference R) concatenated to ``x_t`` at every step."""

    needs_input = True

    def __init__(self, in_channels: int):
        super().__init__()
        self.extra_in_channels = in_channels

    def prepare(self, spatial: Tensor | None) -> Tensor:
        return _check_spatial("ConcatSpatial", spatial, self.extra_in_channels)

    def apply_input(self, x: Tensor, state: Tensor) -> Tensor:
        if state.shape[0] != x.shape[0]:  # one condition shared by a batch of x_t
            state = state.expand(x.shape[0], -1, -1, -1)
        return torch.cat([x, state.to(x.dtype)], dim=1)


#: Spatial components by config name; a new variant registers a builder ``(cfg, channels, **kw) -> component``.
SPATIAL_COMPONENTS: dict[str, Any] = {
    "modulator": lambda cfg, channels, **kw: Modulator(cfg, channels, **kw),
    "concat": lambda cfg, channels, **kw: ConcatSpatial(channels, **kw),
}


def build_spatial(kind: str | None, cfg: UNetConfig, channels: int, **kwargs: Any) -> SpatialConditioning | None:
    """Build the spatial component named ``kind`` (``None``/``"none"``: no spatial conditioning)."""
    if kind is None or kind == "none":
        if channels:
            raise ValueError(f"spatial_type=None but spatial_channels={channels}")
        return None
    if kind not in SPATIAL_COMPONENTS:
        raise KeyError(f"unknown spatial_type {kind!r}; known: {sorted(SPATIAL_COMPONENTS)} or None")
    if channels <= 0:
        raise ValueError(f"spatial_type={kind!r} needs spatial_channels > 0")
    return SPATIAL_COMPONENTS[kind](cfg, channels, **kwargs)


def count_parameters(module: nn.Module | None) -> int:
    """Number of parameters of a module (0 for None)."""
    return 0 if module is None else sum(p.numel() for p in module.parameters())
