"""ControlNet (Zhang et al. 2023) as a spatial component, for the paper's Table IV (conditioning mechanisms).

Follows the official code (lllyasviel/ControlNet, ``cldm/cldm.py``) at pixel level (no latent space):

- a trainable copy of the UNet's encoder (input blocks + middle block, same layout, initialised from the UNet's
  weights as the official ``create_model`` + ``load_state_dict`` does), time-conditioned through the UNet's time
  embedding, with the same non-spatial layers as the UNet (AdaGN's MLP3 in "CN + AdaGN", cross-attention in
  "CN + CA"; the appendix: "injecting the non-spatial vector through AdaGN within each ResNet block");
- a hint encoder (``input_hint_block``: 3x3 convs with SiLU, ending in a zero-initialised conv) whose output is
  added after the copy's first block (the input conv on ``x_t``);
- a zero-initialised 1x1 conv per encoder level and one for the middle block, whose outputs are added to the
  decoder's skip connections and to the middle block's output (``ControlledUnetModel``).

CN-mod (``mod: true``), the paper's "removes only the initial zero-convolution block": no hint encoder; the raw
hint is concatenated to ``x_t`` at the copy's input conv, so the copied encoder sees raw pixels (as the Modulator
does). One class with an option rather than a second registered type, because the two differ in one sub-module
and share everything else (construction, hooks, the per-step cost).

Unlike the Modulator, the copy depends on ``t`` and ``x_t``: ``prepare`` runs only the hint encoder (once per
condition), ``step`` runs the copy at every denoising step, so a relight costs about 1.4x a plain UNet pass per step.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from difareli.errors import UserError

from .conditioning import _check_spatial, register_spatial
from .unet import SpatialConditioning, UNet, build_encoder, zero_module


def hint_encoder(in_channels: int, out_channels: int) -> nn.Sequential:
    """The official ``input_hint_block`` at pixel resolution (no striding: our UNet has no VAE latent):
    conv-SiLU x3 widening 16 -> 32 -> 96, then a zero-initialised 3x3 conv to the first level's width."""
    return nn.Sequential(nn.Conv2d(in_channels, 16, 3, padding=1), nn.SiLU(), nn.Conv2d(16, 32, 3, padding=1),
                         nn.SiLU(), nn.Conv2d(32, 96, 3, padding=1), nn.SiLU(),
                         zero_module(nn.Conv2d(96, out_channels, 3, padding=1)))


@register_spatial("controlnet")
class ControlNet(SpatialConditioning):
    """A ControlNet over ``unet``: residuals added to its skip connections and middle block (see module doc)."""

    needs_input = True

    def __init__(self, unet: UNet, hint_channels: int, mod: bool = False):
        super().__init__()
        cfg = unet.cfg
        self.hint_channels, self.mod = int(hint_channels), bool(mod)
        self.image_channels = unet.in_channels
        emb_dim = 4 * cfg.base_channels
        in_channels = self.image_channels + (self.hint_channels if self.mod else 0)
        self.input_blocks, self.middle_block, skips = build_encoder(cfg, in_channels, emb_dim, unet.nonspatial_dim,
                                                                    unet.cross_attention)
        self.hint_block = None if self.mod else hint_encoder(self.hint_channels, skips[0])
        self.zero_convs = nn.ModuleList(zero_module(nn.Conv2d(c, c, 1)) for c in skips)
        self.middle_zero_conv = zero_module(nn.Conv2d(skips[-1], skips[-1], 1))
        self.level_channels = list(skips) + [skips[-1]]
        self._copy_encoder(unet)

    @torch.no_grad()
    def _copy_encoder(self, unet: UNet) -> None:
        """Start from the UNet's encoder weights; CN-mod's extra hint channels keep their default init."""
        mine = dict(self.input_blocks.named_parameters(prefix="input_blocks"))
        mine.update(self.middle_block.named_parameters(prefix="middle_block"))
        theirs = dict(unet.input_blocks.named_parameters(prefix="input_blocks"))
        theirs.update(unet.middle_block.named_parameters(prefix="middle_block"))
        for name, p in mine.items():
            q = theirs[name]
            if p.shape == q.shape:
                p.copy_(q)
            else:  # CN-mod's input conv: [out, image + hint, 3, 3]; copy the x_t part
                p[:, : q.shape[1]].copy_(q)

    @classmethod
    def build(cls, unet: UNet, channels: int, mod: bool = False, freeze_base: bool = False) -> ControlNet:
        """A ControlNet for ``unet``; ``freeze_base`` stops gradients to the UNet (the usual fine-tuning use; the
        paper trains both jointly from scratch, the default)."""
        if freeze_base:
            unet.requires_grad_(False)
        return cls(unet, channels, mod)

    def validate(self, unet: UNet, image_channels: int) -> None:
        if self.level_channels != unet.encoder_channels:
            raise UserError(f"ControlNet level widths {self.level_channels} do not match the UNet's "
                            f"{unet.encoder_channels}")
        if unet.in_channels != image_channels:
            raise UserError(f"ControlNet adds nothing to x_t, but the UNet takes {unet.in_channels} channels "
                            f"for {image_channels} image channels")

    def prepare(self, spatial: Tensor | None) -> Tensor:
        """The t-independent part, once per condition: the hint features (CN) or the raw hint (CN-mod)."""
        hint = _check_spatial("ControlNet", spatial, self.hint_channels)
        return hint if self.hint_block is None else self.hint_block(hint)

    def step(self, x: Tensor, emb: Tensor, nonspatial: Tensor | None, state: Tensor) -> list[Tensor]:
        """Run the encoder copy on ``x_t`` (+ hint) at this step -> one residual per level (last: middle)."""
        hint = state.to(x.dtype)
        if hint.shape[0] != x.shape[0]:  # one condition shared by a batch of x_t
            hint = hint.expand(x.shape[0], -1, -1, -1)
        h = torch.cat([x, hint], dim=1) if self.mod else x
        residuals = []
        for level, block in enumerate(self.input_blocks):
            h = block(h, emb, nonspatial)
            if level == 0 and not self.mod:
                h = h + hint  # official: the guided hint joins after the first block (the input conv)
            residuals.append(self.zero_convs[level](h))
        residuals.append(self.middle_zero_conv(self.middle_block(h, emb, nonspatial)))
        return residuals

    def modulate(self, level: int, h: Tensor, state: list[Tensor]) -> tuple[Tensor, Tensor]:
        r = state[level]
        if level == len(state) - 1:  # the middle block: its output carries the residual forward
            return h + r, h
        return h, h + r  # encoder levels: the skip connection to the decoder carries it
