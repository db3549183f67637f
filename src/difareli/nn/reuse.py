"""What a prepared condition computes once for every step of an inference sampler (docs/architecture.md, Network).

:class:`ReusedVector` hands the blocks a condition's non-spatial vector so that each AdaGN computes its
``k = MLP3(vector)`` at the first step and reuses it; :func:`allowed` says where a pass may reuse it.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class ReusedVector:
    """A prepared condition's non-spatial vector as the blocks receive it at every step of an inference sampler:
    each AdaGN's ``k = MLP3(vector)`` depends on neither ``t`` nor ``x_t``, so it is computed at the first step and
    reused (kept per module; forgotten if the vector is changed in place)."""

    def __init__(self, vector: Tensor):
        self.vector, self.scales = vector, {}
        self.version = self._version()

    def _version(self) -> int | None:
        return None if self.vector.is_inference() else self.vector._version  # inference tensors keep none

    def scale(self, adagn: nn.Module) -> Tensor:
        if self._version() != self.version:
            self.scales, self.version = {}, self._version()
        if adagn not in self.scales:
            self.scales[adagn] = adagn.mlp(self.vector)
        return self.scales[adagn]


def allowed() -> bool:
    """Whether a pass may reuse what a condition computed at an earlier step: not where autograd records it (training
    needs the MLP3s in each step's graph), nor in a compiled or CUDA-graph-captured pass, whose static inputs take
    the next condition's values in place."""
    return not torch.is_grad_enabled() and not torch.compiler.is_compiling() and not (
        torch.cuda.is_available() and torch.cuda.is_current_stream_capturing())
