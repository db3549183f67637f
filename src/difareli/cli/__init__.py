"""difareli.cli."""
