"""difareli.synth."""
