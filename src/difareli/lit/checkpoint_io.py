"""Checkpoints written atomically in their own folder (Lightning ``CheckpointIO``).

Lightning's default writer goes through an fsspec transaction whose temporary file lives in the system temporary
folder; when the run folder is on another filesystem the commit is a copy, so a kill during it leaves a torn
``last.ckpt``. This one writes beside the target, fsyncs, and renames (:func:`difareli.fileio.torch_save_atomic`):
a kill at any moment leaves the previous checkpoint loadable, and a full disk names the checkpoint.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lightning.pytorch.plugins.io import TorchCheckpointIO

from difareli.fileio import torch_save_atomic


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose saves are atomic renames within the checkpoint's folder (local paths)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options")
        if "://" in str(path):  # a remote filesystem: Lightning's own writer knows it
            return super().save_checkpoint(checkpoint, path)
        torch_save_atomic(checkpoint, Path(path), durable=True)
