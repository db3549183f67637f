"""One runtime: device, precision, compile, CUDA graphs, memory format; the inference copy."""
