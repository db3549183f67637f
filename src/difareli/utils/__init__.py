"""Utilities every layer may use: atomic file I/O, image operations, lazy imports, processes, figures."""
