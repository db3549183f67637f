"""Performance measurement: untrained models for timing, the sampler speed/quality benchmark."""
