"""LightningModules and their checkpoints."""

from difareli.checkpoints.loading import LoadedCheckpoint, load_checkpoint
from difareli.lit.diffusion import DiffusionModule

__all__ = ["DiffusionModule", "LoadedCheckpoint", "load_checkpoint"]
