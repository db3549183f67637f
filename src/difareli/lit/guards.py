"""Training guards: a non-finite loss or gradient stops training before it poisons the weights.

The check runs before ``backward`` (loss) and before the optimizer step (gradients), so the step that would
write NaN into the parameters never happens and ModelCheckpoint (which saves after the batch) never saves a
poisoned ``last.ckpt``: the last good checkpoint stays as it was.
"""

from __future__ import annotations

import math
from typing import Any

import lightning as L
import torch

from difareli.errors import UserError


class NonFiniteLossError(UserError):
    """The training loss or gradients became NaN/Inf; the message names the batch's records."""


class NonFiniteGuard(L.Callback):
    """Stop training on a non-finite loss (and, with ``check_gradients``, non-finite gradients)."""

    def __init__(self, check_gradients: bool = True, max_ids: int = 16):
        self.check_gradients, self.max_ids = check_gradients, max_ids
        self._ids: list[str] = []
        self._batch_idx = -1

    def on_train_batch_start(self, trainer, pl_module, batch: Any, batch_idx: int) -> None:
        ids = batch.get("record_id") if isinstance(batch, dict) else None
        self._ids = [str(i) for i in ids] if ids is not None else []
        self._batch_idx = batch_idx

    def _fail(self, trainer, what: str) -> None:
        shown = ", ".join(self._ids[: self.max_ids]) + (" ..." if len(self._ids) > self.max_ids else "")
        raise NonFiniteLossError(
            f"{what} at step {trainer.global_step} (batch {self._batch_idx}, records: {shown or 'unknown'}); "
            "training stopped, checkpoints left as they were\n"
            "check those records (difareli-store verify <store>) or lower the learning rate, then resume from "
            "last.ckpt")

    def on_before_backward(self, trainer, pl_module, loss: torch.Tensor) -> None:
        if not bool(torch.isfinite(loss.detach()).all()):
            self._fail(trainer, f"training loss is {float(loss.detach().float().reshape(-1)[0])}")

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx: int) -> None:
        # Finite loss and gradients can still step into Inf weights (e.g. an absurd learning rate); this runs
        # before ModelCheckpoint's hook (Lightning calls checkpoint callbacks last), so nothing poisoned is saved.
        params = [p.detach() for p in pl_module.parameters()]
        if params and not bool(torch.stack([torch.isfinite(p).all() for p in params]).all()):
            self._fail(trainer, "the weights became non-finite after the optimizer step")

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        # fp16 loss scaling makes inf gradients on purpose (the scaler then skips the step): not an error.
        if not self.check_gradients or str(trainer.precision).startswith("16"):
            return
        norms = [p.grad.detach().float().norm() for g in optimizer.param_groups for p in g["params"]
                 if p.grad is not None]
        if norms:
            total = float(torch.stack(norms).norm())
            if not math.isfinite(total):
                self._fail(trainer, f"gradient norm is {total}")
