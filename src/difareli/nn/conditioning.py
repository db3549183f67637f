"""Spatial-conditioning components plugged into the UNet's hooks (SPEC 4, ablations SPEC 9).

A component subclasses :class:`~difareli.nn.unet.SpatialConditioning`: ``prepare(spatial)`` runs once per condition
and returns a state; the UNet then calls ``step`` / ``apply_input`` / ``modulate(level, h, state)`` at every step.
Variants are new components, never UNet edits. A component registers itself under its config ``type``
(:func:`register_spatial`); a model config names it as ``spatial: {type: modulator, modulate_skips: false}`` and
the options go to the class's ``build(unet, channels, **options)``:

- :class:`Modulator` (DiFaReli, DiFaReli++): a time-free copy of the UNet's first half; ``o_i' = o_i * tanh(m_i)``.
- :class:`ConcatSpatial` (ablation (a), "no Modulator"): the spatial input concatenated to ``x_t`` at every step.
- A ControlNet (ablation, later) fits as: ``step`` runs its time-conditioned encoder copy on ``x_t`` plus the hint
  and returns per-level residuals; ``modulate`` returns ``(h, h + residual)`` for input levels (skip path) and
  ``(h + residual, h)`` for the middle level. Cross-attention non-spatial conditioning would instead give the
  UNet's attention blocks a context; it is independent of these hooks.

Non-spatial AdaGN conditioning (the per-block MLP3s) lives in the UNet's residual blocks (``unet.AdaGN``).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import Tensor, nn

from difareli.errors import MissingError, UserError

from .unet import SpatialConditioning, UNet, UNetConfig, build_encoder

__all__ = ["SPATIAL_COMPONENTS", "ConcatSpatial", "Modulator", "SpatialConditioning", "register_spatial",
           "resolve_spatial"]

#: Spatial components by config ``type``; filled by :func:`register_spatial`.
SPATIAL_COMPONENTS: dict[str, type[SpatialConditioning]] = {}


def register_spatial(name: str) -> Callable[[type[SpatialConditioning]], type[SpatialConditioning]]:
    """Class decorator: make a :class:`SpatialConditioning` subclass available as ``spatial: {type: name}``."""

    def register(cls: type[SpatialConditioning]) -> type[SpatialConditioning]:
        if name in SPATIAL_COMPONENTS and SPATIAL_COMPONENTS[name] is not cls:
            raise UserError(f"spatial type {name!r} is already registered by {SPATIAL_COMPONENTS[name].__name__}")
        SPATIAL_COMPONENTS[name] = cls
        cls.type_name = name
        return cls

    return register


def resolve_spatial(spec: str | Mapping[str, Any] | None, channels: int
                    ) -> tuple[type[SpatialConditioning] | None, dict[str, Any]]:
    """``(component class, options)`` for a spatial spec: ``None`` (no spatial conditioning), a registered type
    name, or a mapping ``{type: <name>, <option>: <value>, ...}``; checks the options against ``build``."""
    if spec is None or spec == "none":
        if channels:
            raise UserError(f"model.spatial is null but the spatial inputs have {channels} channels; "
                            "set model.spatial.type or model.spatial_inputs=[]")
        return None, {}
    options = {"type": spec} if isinstance(spec, str) else dict(spec)
    kind = options.pop("type", None)
    if kind not in SPATIAL_COMPONENTS:
        raise MissingError(f"unknown spatial type {kind!r} (model.spatial.type); known: {sorted(SPATIAL_COMPONENTS)} "
                           "or model.spatial=null")
    cls = SPATIAL_COMPONENTS[kind]
    if channels <= 0:
        raise UserError(f"spatial type {kind!r} needs spatial inputs (model.spatial_inputs), got 0 channels")
    accepted = [p for p in inspect.signature(cls.build).parameters if p not in ("unet", "channels")]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise UserError(f"spatial type {kind!r} has no option(s) {unknown}; its options: {accepted}")
    return cls, options


def _check_spatial(name: str, spatial: Tensor | None, channels: int) -> Tensor:
    if spatial is None:
        raise UserError(f"{name} needs a spatial input with {channels} channels, got None")
    if spatial.ndim != 4 or spatial.shape[1] != channels:
        raise UserError(f"{name} expects spatial [B, {channels}, H, W], got {tuple(spatial.shape)}")
    return spatial


@register_spatial("modulator")
class Modulator(SpatialConditioning):
    """DiFaReli's Modulator: the UNet's first half (input conv, input blocks, middle block), separate weights, no t.

    Its output at level ``i`` (``m_i``, same shape as the UNet's ``o_i``) gates the UNet's forward path,
    ``o_i' = o_i * tanh(m_i)``. By default the skip connection keeps the unmodulated ``o_i`` (public code);
    ``modulate_skips=True`` sends ``o_i'`` to the decoder too. The state holds ``tanh(m_i)``, computed once.
    """

    needs_input = True

    def __init__(self, cfg: UNetConfig, in_channels: int, modulate_skips: bool = False):
        super().__init__()
        self.in_channels, self.modulate_skips = in_channels, bool(modulate_skips)
        self.input_blocks, self.middle_block, skips = build_encoder(cfg, in_channels, emb_dim=0, nonspatial_dim=0)
        self.level_channels = list(skips) + [skips[-1]]  # per level, the middle block keeps the last width

    @classmethod
    def build(cls, unet: UNet, channels: int, modulate_skips: bool = False) -> Modulator:
        """A Modulator mirroring ``unet``'s encoder layout (its own weights)."""
        return cls(unet.cfg, channels, modulate_skips)

    def validate(self, unet: UNet, image_channels: int) -> None:
        if self.level_channels != unet.encoder_channels:
            raise UserError(f"Modulator level widths {self.level_channels} do not match the UNet's "
                            f"{unet.encoder_channels}")

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


@register_spatial("concat")
class ConcatSpatial(SpatialConditioning):
    """Ablation (a): the spatial input (e.g. the shading reference R) concatenated to ``x_t`` at every step."""

    needs_input = True

    def __init__(self, in_channels: int):
        super().__init__()
        self.in_channels = in_channels

    @classmethod
    def extra_input_channels(cls, channels: int, **options: Any) -> int:
        return channels

    @classmethod
    def build(cls, unet: UNet, channels: int) -> ConcatSpatial:
        return cls(channels)

    def validate(self, unet: UNet, image_channels: int) -> None:
        if unet.in_channels != image_channels + self.in_channels:
            raise UserError(f"ConcatSpatial adds {self.in_channels} channels to {image_channels}, but the UNet "
                            f"takes {unet.in_channels}")

    def prepare(self, spatial: Tensor | None) -> Tensor:
        return _check_spatial("ConcatSpatial", spatial, self.in_channels)

    def apply_input(self, x: Tensor, state: Tensor) -> Tensor:
        if state.shape[0] != x.shape[0]:  # one condition shared by a batch of x_t
            state = state.expand(x.shape[0], -1, -1, -1)
        return torch.cat([x, state.to(x.dtype)], dim=1)


def count_parameters(module: nn.Module | None) -> int:
    """Number of parameters of a module (0 for None)."""
    return 0 if module is None else sum(p.numel() for p in module.parameters())
