"""difareli: DiFaReli++ face relighting (diffusion with consistent cast shadows), Lightning + Hydra."""

from difareli.checkpoints import loading as _loading

__version__ = "0.1.0"


def _models() -> None:
    import difareli.lit  # noqa: F401  (its models register themselves with the checkpoint loader)


# The package's root hands the checkpoint loader, once, how its model classes load: a checkpoint names its class and
# the loader looks it up (difareli.checkpoints.loading); Lightning loads only when a checkpoint is first read.
_loading.provide(_models)
