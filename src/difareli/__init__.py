"""difareli: DiFaReli++ face relighting (diffusion with consistent cast shadows), Lightning + Hydra."""

__version__ = "0.1.0"
