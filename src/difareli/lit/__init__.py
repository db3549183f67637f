"""LightningModules and their checkpoints: importing it registers the model classes a checkpoint names
(:mod:`difareli.checkpoints.loading`)."""

from difareli.checkpoints.loading import LoadedCheckpoint, load_checkpoint
from difareli.lit.diffusion import DiffusionModule
from difareli.lit.student import StudentModule

__all__ = ["DiffusionModule", "LoadedCheckpoint", "StudentModule", "load_checkpoint"]
