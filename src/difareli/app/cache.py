"""The cancel check that lets an abandoned relight give the app's lock back."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from .checks import RequestError


class Cancelled(RequestError):
    """The client gave up (closed its connection) while its request waited or ran."""

    def __init__(self, what: str = "the request"):
        super().__init__(f"{what} was cancelled: the client closed the connection", 499)


class CancelScope:
    """The current request's "has the client gone?" check, read between network passes (a forward pre-hook on
    the denoising network, so once per sampler step) and while waiting for the lock. Only the request holding
    the lock sets it, so one slot is enough; a deep copy of a hooked network shares it."""

    def __init__(self) -> None:
        self.check: Callable[[], bool] | None = None
        self.cancelled = 0  # how many requests were cancelled (tests, logs)

    def __deepcopy__(self, memo: dict) -> "CancelScope":
        # The runtime's inference copy (bf16 on a CPU with native bf16) deep-copies the network with its hooks; a
        # copied scope would keep the check of the request that made the copy, whose socket is closed by the next
        # one, and cancel every later relight. The copy's hook must read this one scope.
        return self

    def hook(self, module: Any, args: Any) -> None:
        """``nn.Module.register_forward_pre_hook`` callback: stop the pass if the client has gone."""
        check = self.check
        if check is not None and check():
            self.cancelled += 1
            raise Cancelled("the relight")

    def acquire(self, lock: threading.Lock, gone: Callable[[], bool] | None, poll: float = 0.2) -> None:
        """Take ``lock``, giving up (:class:`Cancelled`) when the waiting client goes."""
        while not lock.acquire(timeout=poll):
            if gone is not None and gone():
                self.cancelled += 1
                raise Cancelled()


def attach(model: Any, scope: CancelScope) -> None:
    """Hook ``scope`` onto the network a sampler calls once per step (``model.net``; the model itself for a
    module without one). Inference copies made by the runtime are deep copies, which keep the hook."""
    import torch

    net = getattr(model, "net", model)
    if isinstance(net, torch.nn.Module):
        net.register_forward_pre_hook(scope.hook)
