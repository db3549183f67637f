"""The network as low-precision inference runs it: convolution and linear weights cast once, channels-last.

Under autocast every convolution and linear layer casts its fp32 weight to bf16 on every call (PyTorch's weight
cast cache only serves autograd, and only inside one autocast region); at ffhq128 that is 149 M values read and
written per network pass. :func:`inference_copy` keeps one copy of a network whose Conv/Linear weights and biases
are already in the autocast dtype (the values autocast would produce: bit for bit the same convolution inputs)
and, optionally, in channels-last layout (oneDNN's native layout for bf16 on a CPU: NCHW inputs are reordered
inside every convolution, forward and backward). Normalisation parameters stay float32, as autocast leaves them.

The copy belongs to the runtime (:meth:`difareli.runtime.core.Runtime.denoiser`); the caller's network is never
changed. It is refreshed in place whenever a parameter or buffer of the original changed since it was made (a
training step, ``load_state_dict``, an EMA swap: tracked by the tensors' version counters and storage), so
a relight never runs stale weights, and a compiled copy stays valid.
"""

from __future__ import annotations

import copy
import weakref
from typing import Any

import torch
import torch.utils._pytree as pytree
from torch import Tensor, nn

#: Layers whose weights autocast casts to the low-precision dtype (its lower-precision op list).
CAST_LAYERS = (nn.Conv1d, nn.Conv2d, nn.Conv3d, nn.ConvTranspose2d, nn.Linear)

# original network -> {(dtype, channels_last): _Copy}. Weak keys: a dropped network drops its copies.
_COPIES: "weakref.WeakKeyDictionary[nn.Module, dict]" = weakref.WeakKeyDictionary()


def _state(net: nn.Module) -> tuple:
    """What identifies the original's current values: each tensor's storage and in-place version."""
    return tuple((t.data_ptr(), t._version) for t in [*net.parameters(), *net.buffers()])


class _Copy:
    def __init__(self, net: nn.Module, dtype: torch.dtype | None, channels_last: bool):
        self.module = copy.deepcopy(net).eval().requires_grad_(False)
        self.dtype, self.channels_last = dtype, channels_last
        self._convert()
        self.state = _state(net)

    def _convert(self) -> None:
        for m in self.module.modules():
            if self.dtype is not None and isinstance(m, CAST_LAYERS):
                for name in ("weight", "bias"):
                    p = getattr(m, name, None)
                    if p is not None:
                        p.data = p.data.to(self.dtype)
        if self.channels_last:
            self.module.to(memory_format=torch.channels_last)

    def refresh(self, net: nn.Module) -> None:
        """Copy the original's current values in (dtype and layout kept): the copy's tensors stay the same."""
        with torch.no_grad():
            mine = [*self.module.parameters(), *self.module.buffers()]
            theirs = [*net.parameters(), *net.buffers()]
            if len(mine) != len(theirs) or any(a.shape != b.shape for a, b in zip(mine, theirs)):
                raise RuntimeError("the network's structure changed since its inference copy was made; "
                                   "call difareli.runtime.core.clear_caches(net)")
            for a, b in zip(mine, theirs):
                a.copy_(b)
        self.state = _state(net)


def inference_copy(net: nn.Module, dtype: torch.dtype | None, channels_last: bool) -> nn.Module:
    """The cached copy of ``net`` with Conv/Linear weights in ``dtype`` (None: as they are) and, if asked,
    channels-last; refreshed from ``net`` if its values changed since the last call."""
    copies = _COPIES.setdefault(net, {})
    key = (dtype, channels_last)
    entry = copies.get(key)
    if entry is None:
        entry = copies[key] = _Copy(net, dtype, channels_last)
    elif entry.state != _state(net):
        entry.refresh(net)
    return entry.module


def forget(net: nn.Module | None = None) -> None:
    """Drop the inference copies of one network, or of all."""
    if net is None:
        _COPIES.clear()
    else:
        _COPIES.pop(net, None)


def to_channels_last(tree: Any) -> Any:
    """Every 4-D tensor of a (nested) condition in channels-last layout; anything else as it is."""
    return pytree.tree_map(lambda v: v.contiguous(memory_format=torch.channels_last)
                           if isinstance(v, Tensor) and v.dim() == 4 else v, tree)
