"""Data: the encoding registry, the store, derived encodings, shards, provenance, protocols, inputs."""
