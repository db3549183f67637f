"""Checkpoints written atomically in their own folder (Lightning ``CheckpointIO``).

Lightning's default writer goes through an fsspec transaction whose temporary file lives in the system temporary
folder; when the run folder is on another filesystem the commit is a copy, so a kill during it leaves a torn
``last.ckpt``. This one writes beside the target, fsyncs, and renames (:func:`difareli.utils.fileio.torch_save_atomic`):
a kill at any moment leaves the previous checkpoint loadable, and a full disk names the checkpoint.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO

from difareli.utils.fileio import torch_save_atomic


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose saves are atomic renames within the checkpoint's folder (local paths)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options")
        if "://" in str(path):  # a remote filesystem: Lightning's own writer knows it
            return super().save_checkpoint(checkpoint, path)
        torch_save_atomic(checkpoint, Path(path), durable=True)


class StopAwareModelCheckpoint(ModelCheckpoint):
    """Lightning's ``ModelCheckpoint`` that also writes ``last.ckpt`` at the step where training stops.

    Lightning saves ``last`` at train end only when no ``last`` was ever written, so a run stopped by ``max_time``
    (or by a ``max_steps`` that is not a multiple of ``every_n_train_steps``) loses every step after its last
    periodic checkpoint. Saving in the stopping batch's hook, not at train end, keeps the raw weights as the resume
    state: at train end the EMA callback has already copied its average into the model.
    """

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        stopping = trainer.should_stop or (0 < trainer.max_steps <= trainer.global_step)
        if (not stopping or not self.save_last or self._last_global_step_saved == trainer.global_step
                or self._should_skip_saving_checkpoint(trainer)):
            return
        # Leave the step unmarked as saved: a validation that follows at this step still writes its top-k
        # checkpoint (and last again), which Lightning skips for a step it has already saved.
        marked = self._last_global_step_saved
        self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
        self._last_global_step_saved = marked
