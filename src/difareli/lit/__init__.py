"""LightningModules and their checkpoints."""

from difareli.lit.checkpoint import LoadedCheckpoint, load_checkpoint
from difareli.lit.diffusion import DiffusionModule

__all__ = ["DiffusionModule", "LoadedCheckpoint", "load_checkpoint"]
