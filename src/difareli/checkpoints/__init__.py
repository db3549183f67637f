"""Checkpoints: the keys difareli writes, the shipped zoo (weights beside this file), loading."""
