"""The one line difareli-train ends with: steps done of planned, why it stopped, the checkpoint, the next command.

A run cut short by its time limit (``experiment=quickstart`` has ``max_time``) used to end like a finished one; this
line says which it was and how to go on.
"""

from __future__ import annotations

import math
import shlex
from datetime import timedelta
from typing import Any, Sequence

from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint, Timer


def planned_steps(trainer) -> int | None:
    """The optimizer steps this fit was set to run: ``max_steps``, else what ``max_epochs`` amounts to."""
    if trainer.max_steps and trainer.max_steps > 0:
        return int(trainer.max_steps)
    try:
        est = trainer.estimated_stepping_batches
    except Exception:  # an endless or unsized loader: no plan to state, the line says "of ?"
        return None
    return int(est) if math.isfinite(est) else None


def stop_reason(trainer) -> str:
    """Why ``trainer.fit`` returned, in the setting's own words: ``interrupted``, ``max_steps=N``,
    ``max_time=D``, ``early stop on <metric>``, ``max_epochs=N`` or ``fast_dev_run``."""
    if trainer.interrupted:
        return "interrupted"
    if trainer.fast_dev_run:
        return f"fast_dev_run={trainer.fast_dev_run}"
    if 0 < trainer.max_steps <= trainer.global_step:
        return f"max_steps={trainer.max_steps}"
    for cb in trainer.callbacks:
        if isinstance(cb, Timer) and cb.time_remaining() is not None and cb.time_remaining() <= 0:
            return f"max_time={timedelta(seconds=round(cb._duration))}"  # Timer keeps the limit in seconds only
        if isinstance(cb, EarlyStopping) and cb.stopped_epoch > 0:
            return f"early stop on {cb.monitor}"
    if trainer.max_epochs is not None and 0 < trainer.max_epochs <= trainer.current_epoch:
        return f"max_epochs={trainer.max_epochs}"
    return "stopped by a callback" if trainer.should_stop else "the training loop ended"


def checkpoint_path(trainer, resumed_from: Any = None) -> str | None:
    """The checkpoint to continue from: this run's ``last.ckpt``, else the one it resumed from (a run stopped before
    its first save; Lightning reloads that run's best path only), else the best one; None without any."""
    saved = [cb for cb in trainer.callbacks if isinstance(cb, ModelCheckpoint)]
    last = next((cb.last_model_path for cb in saved if cb.last_model_path), None)
    best = next((cb.best_model_path for cb in saved if cb.best_model_path), None)
    return last or (str(resumed_from) if resumed_from else None) or best


def next_command(reason: str, ckpt: str | None, overrides: Sequence[str], store: Any) -> str:
    """Resume (a run cut short) or relight (a run that finished) with the checkpoint."""
    cut = reason == "interrupted" or reason.startswith("max_time")
    if ckpt is None:
        if reason.startswith("fast_dev_run"):
            return "none (fast_dev_run writes no checkpoint: train without it (debug=fdr sets it))"
        return ("rerun with a longer trainer.max_time (stopped before its first checkpoint)" if cut
                else "none (no checkpoint written: is callbacks.model_checkpoint off?)")
    if cut:
        kept = [o for o in overrides if not o.startswith(("ckpt_path=", "trainer.max_time=", "init_from="))]
        # The Timer's elapsed time is in the checkpoint: resuming under the same max_time would stop at once.
        extra = ["trainer.max_time=null"] if reason.startswith("max_time") else []
        return "resume: " + shlex.join(["difareli-train", *kept, f"ckpt_path={ckpt}", *extra])
    where = [f"store={store}"] if store else []
    return "relight: " + shlex.join(["difareli-relight", f"checkpoint={ckpt}", *where, "target.yaw=45"])


def train_summary(trainer, overrides: Sequence[str] = (), store: Any = None, resumed_from: Any = None) -> str:
    """``train: 97 of 300 steps, stopped by max_time=0:03:45; checkpoint <path>; next: resume: difareli-train ...``"""
    planned = planned_steps(trainer)
    reason = stop_reason(trainer)
    ckpt = checkpoint_path(trainer, resumed_from)
    return (f"train: {trainer.global_step} of {planned if planned is not None else '?'} steps, stopped by {reason}; "
            f"checkpoint {ckpt or 'none'}; next: {next_command(reason, ckpt, overrides, store)}")
