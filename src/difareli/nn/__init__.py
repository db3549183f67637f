"""difareli.nn."""
