"""difareli.diffusion."""
