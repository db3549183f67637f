"""Shared test fixtures."""

import os

import numpy as np
import pytest
import torch

# Two cores: keep intra-op threads modest so parallel helpers/tests do not oversubscribe.
torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def synth_store(tmp_path_factory):
    """A small SynthFaces store (8 subjects x 2 lights, 32 px), generated once per test session."""
    from difareli.synth.generator import generate

    root = tmp_path_factory.mktemp("synthfaces") / "store"
    generate(out_dir=str(root), subjects=8, lights=2, resolution=32, seed=0)
    return root
