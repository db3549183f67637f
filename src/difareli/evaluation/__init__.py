"""Measuring relights: metrics, tables, the benchmark and its baselines, measured videos."""
