"""difareli.lit."""
