"""Relighting with any sampler: invert with the input's own condition, then decode under targets (SPEC 5).

Three passes per image, all sampler-agnostic:

1. inversion ``x_0 -> x_T`` on the ascending grid, recording per-channel spatial means of each ``x_t``;
2. (mean-matching) a self-decode ``x_T -> x_0`` with the input's own condition, recording the same means;
   the per-step offsets ``mu_t = mean(x_t^inv) - mean(x_t^self)`` are kept in the :class:`Inversion`;
3. the decode under one or many target conditions, adding ``mu_t`` after each step.

Passes 1-2 run once per image; any number of targets can then be decoded, in one batch. These functions work
on denoisers; :mod:`difareli.relight.relighter` runs them for models (conditions, runtime, records).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from difareli.diffusion.schedule import DiffusionSchedule
from difareli.diffusion.spec import SamplerSpec
from difareli.errors import UserError

Denoiser = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _channel_means(x: torch.Tensor) -> torch.Tensor:
    return x.float().mean(dim=(2, 3))


@dataclass
class Inversion:
    """The result of passes 1-2 for a batch of images: ``x_T`` and the mean-matching offsets.

    ``offsets[i]`` ([B, C]) is added after decode step ``i``; ``None`` when mean-matching is off.
    """

    x_T: torch.Tensor
    spec: SamplerSpec
    offsets: torch.Tensor | None

    def repeat_each(self, k: int) -> "Inversion":
        """Each image's inversion repeated for its ``k`` targets, image-major (batch of B -> B x k)."""
        off = None if self.offsets is None else self.offsets.repeat_interleave(k, 1)
        return Inversion(self.x_T.repeat_interleave(k, 0), self.spec, off)

    def expand(self, n: int) -> "Inversion":
        """The same inversion repeated for ``n`` targets of one image (batch of 1 -> n)."""
        if self.x_T.shape[0] != 1:
            raise UserError(f"expand() needs an inversion of one image, got a batch of {self.x_T.shape[0]}")
        off = None if self.offsets is None else self.offsets.expand(-1, n, -1)
        return Inversion(self.x_T.expand(n, -1, -1, -1).contiguous(), self.spec, off)


@torch.no_grad()
def invert(denoiser: Denoiser, x0: torch.Tensor, schedule: DiffusionSchedule, spec: SamplerSpec, *,
           mean_matching: bool = True, progress: bool = False) -> Inversion:
    """Passes 1-2: invert ``x0`` with its own condition (bound in ``denoiser``) and, with mean-matching,
    self-decode to compute the per-step offsets once."""
    inv_grid, gen_grid = spec.grids(schedule)
    means = [_channel_means(x0)]

    def record_inv(step, t, t_next, x):
        means.append(_channel_means(x))

    x_T = spec.run(denoiser, x0, inv_grid, schedule, clip_x0=spec.clip_x0_invert,
                   callback=record_inv if mean_matching else None, progress=progress)
    if not mean_matching:
        return Inversion(x_T, spec, None)
    # Decode step i lands on gen_grid[i + 1] = inv_grid[n - 1 - i], where the inversion recorded means[n-1-i].
    target = means[::-1][1:]
    offsets = []

    def match(step, t, t_next, x):
        # Offsets are measured on the *matched* self-decode (each applied before the next is measured), so
        # decoding with the input's own condition reproduces the inversion's means at every step; measuring
        # them on an unmatched decode and adding them cumulatively would over-correct.
        mu = target[step] - _channel_means(x)
        offsets.append(mu)
        return x + mu.to(x.dtype)[:, :, None, None]

    spec.run(denoiser, x_T, gen_grid, schedule, clip_x0=spec.clip_x0_generate, callback=match, progress=progress)
    offsets = torch.stack(offsets)
    return Inversion(x_T, spec, offsets)


def guided(target: Denoiser, source: Denoiser, scale: float) -> Denoiser:
    """Light guidance: ``eps_s + scale * (eps_t - eps_s)`` of a target and a source denoiser on the same batch
    (``scale`` 1: the target's eps itself, not recomputed)."""
    if scale == 1.0:
        return target

    def denoiser(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        eps_s = source(x, t)
        return eps_s + scale * (target(x, t) - eps_s)

    return denoiser


@torch.no_grad()
def decode(denoiser: Denoiser, inversion: Inversion, schedule: DiffusionSchedule, *, progress: bool = False,
           callback=None, source: Denoiser | None = None) -> torch.Tensor:
    """Pass 3: decode ``inversion.x_T`` with the (target) condition bound in ``denoiser``, adding the
    mean-matching offsets after each step. ``callback(step, t, t_next, x)`` sees the matched ``x``. With the
    spec's ``guidance`` w != 1, ``source`` (the input's own condition, batched as the targets) guides each step
    (:func:`guided`)."""
    _, gen_grid = inversion.spec.grids(schedule)
    offsets = inversion.offsets
    if inversion.spec.guidance != 1.0:
        if source is None:
            raise UserError(f"sampler guidance={inversion.spec.guidance} needs the source's denoiser beside the "
                            "target's (difareli.relight.core.relight passes it)")
        denoiser = guided(denoiser, source, inversion.spec.guidance)

    def step_hook(step, t, t_next, x):
        if offsets is not None:
            x = x + offsets[step].to(x.dtype)[:, :, None, None]
        if callback is not None:
            out = callback(step, t, t_next, x)
            x = x if out is None else out
        return x

    return inversion.spec.run(denoiser, inversion.x_T, gen_grid, schedule, clip_x0=inversion.spec.clip_x0_generate,
                              callback=step_hook, progress=progress)
