"""The tensor-level relight (SPEC 5): one image, its own condition, many target conditions, one batch.

:func:`relight` inverts with the input's own condition (mean-matching offsets computed once,
:mod:`difareli.diffusion.relight`) and decodes every target in one batch, or runs a one-pass model once per target;
:func:`invert_image` is passes 1-2 alone. Low in the house (protocols, runtime, samplers only), so the relighting
core (:mod:`difareli.relight.relighter`), the training callbacks, jobs and benchmarks all call the same function.
"""

from __future__ import annotations

import inspect
from typing import Any

import torch
from torch import Tensor

from difareli.diffusion.relight import Inversion, SamplerSpec, decode, invert
from difareli.data.inputs import Condition
from difareli.relight.relightable import DiffusionRelightable, OnePassRelightable, Relightable
from difareli.runtime.core import Runtime
from difareli.errors import UserError


def _denoiser(model: DiffusionRelightable, cond: Any, runtime: Runtime | None):
    forward = getattr(model, "net", None)
    if runtime is None or forward is None:
        return model.denoiser(cond)
    return runtime.denoiser(forward, cond)


def _takes_runtime(model: Relightable) -> bool:
    # As diffusers asks a scheduler's step() whether it takes ``generator``: the argument is optional in the protocol.
    return "runtime" in inspect.signature(model.relight_once).parameters


def _condition(model: Relightable, inputs: Condition, runtime: Runtime | None):
    if runtime is None:
        return model.condition(*inputs)
    with runtime.autocast():
        return model.condition(*inputs)


@torch.no_grad()
def invert_image(model: DiffusionRelightable, x0: Tensor, source: Condition, spec: SamplerSpec, *,
                 runtime: Runtime | None = None, mean_matching: bool = True, progress: bool = False) -> Inversion:
    """Passes 1-2 for one image: inversion with its own condition and the mean-matching offsets."""
    den = _denoiser(model, _condition(model, source, runtime), runtime)
    return invert(den, x0, model.schedule, spec, mean_matching=mean_matching, progress=progress)


@torch.no_grad()
def relight(model: Relightable, x0: Tensor, source: Condition, targets: Condition, spec: SamplerSpec | None = None,
            *, runtime: Runtime | None = None, mean_matching: bool = True, inversion: Inversion | None = None,
            progress: bool = False) -> Tensor:
    """Relight one image ``x0`` [1, 3, H, W] under ``B`` targets in one batch -> [B, 3, H, W] float.

    ``source`` is the input's own condition (batch 1), ``targets`` batch ``B``. A diffusion model inverts once
    (or reuses ``inversion``) and decodes every target in one batch: the Modulator runs once for the source and
    once for the targets. A one-pass model maps the image in one network pass per target.
    """
    n = next(v.shape[0] for v in targets if v is not None)
    if isinstance(model, OnePassRelightable):
        src = tuple(None if v is None else v.expand(n, *v.shape[1:]) for v in source)
        args = (x0.expand(n, -1, -1, -1), model.condition(*src), model.condition(*targets))
        if runtime is None:
            return model.relight_once(*args).float()
        if _takes_runtime(model):  # its pass runs through runtime.denoiser (weights cast once, channels-last)
            return model.relight_once(*args, runtime=runtime).float()
        with runtime.autocast():  # a one-pass model written without the runtime argument
            return model.relight_once(*args).float()
    if spec is None:
        raise UserError(f"{type(model).__name__} is a diffusion model: relighting it needs a sampler spec")
    if inversion is None:
        inversion = invert_image(model, x0, source, spec, runtime=runtime, mean_matching=mean_matching,
                                 progress=progress)
    den = _denoiser(model, _condition(model, targets, runtime), runtime)
    src = None
    if inversion.spec.guidance != 1.0:  # the source condition beside each target (targets are source-major)
        rep = n // next(v.shape[0] for v in source if v is not None)
        batched = tuple(None if v is None else v.repeat_interleave(rep, 0) for v in source)
        src = _denoiser(model, _condition(model, batched, runtime), runtime)
    return decode(den, inversion.expand(n) if inversion.x_T.shape[0] != n else inversion, model.schedule,
                  progress=progress, source=src)
