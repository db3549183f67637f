"""difareli.render."""
