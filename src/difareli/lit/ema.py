"""The EMA of the weights: Lightning's ``EMAWeightAveraging`` with an optional decay warm-up.

With a fixed decay of 0.999 the average of a short run is mostly its first, untrained weights: at step 500 about
``0.999**500 = 61%`` of the average is still the initialisation (the step-500 SynthFaces v3 DiFaReli of
docs/synthfaces_v3.md: its EMA weights barely responded to c while its raw weights did). ``warmup=true`` uses
the decay ``min(decay, (1 + n) / (10 + n))`` after ``n`` updates (the schedule of diffusers' ``EMAModel`` and
timm's ``ModelEmaV2`` warm-up), so the average forgets the initialisation within the first few hundred steps and
reaches the full decay later (0.999 after ~9,000 updates).
"""

from __future__ import annotations

from typing import Any

import torch
from lightning.pytorch.callbacks import EMAWeightAveraging
from torch import Tensor

from difareli.errors import UserError


def warmup_decay(decay: float, n_averaged: int) -> float:
    """The decay of the update after ``n_averaged`` updates: ``min(decay, (1 + n) / (10 + n))``."""
    return min(decay, (1.0 + n_averaged) / (10.0 + n_averaged))


def ema_warmup_avg_fn(decay: float):
    """``AveragedModel``'s ``avg_fn`` for an EMA whose decay warms up (see :func:`warmup_decay`)."""
    if not 0.0 <= decay <= 1.0:
        raise UserError(f"EMA decay must lie in [0, 1], got {decay}")

    @torch.no_grad()
    def update(ema_param: Tensor, current_param: Tensor, num_averaged: Tensor) -> Tensor:
        d = warmup_decay(decay, int(num_averaged))
        return d * ema_param + (1.0 - d) * current_param

    return update


class EMA(EMAWeightAveraging):
    """Lightning's EMA callback (checkpoints hold the average in ``state_dict``, the raw weights in
    ``current_model_state``); ``warmup=True`` warms the decay up (module docstring)."""

    def __init__(self, decay: float = 0.999, warmup: bool = False, **kwargs: Any):
        super().__init__(decay=decay, **kwargs)
        self.decay, self.warmup = decay, warmup
        if warmup:
            self._kwargs["avg_fn"] = ema_warmup_avg_fn(decay)

    @property
    def state_key(self) -> str:
        # The key Lightning files this callback's state under in a checkpoint: the parent's, so runs written with
        # lightning's EMAWeightAveraging in the config resume with this one.
        return "EMAWeightAveraging"
