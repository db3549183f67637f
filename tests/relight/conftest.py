"""Fixtures of the relight tests: the SynthFaces store with extreme input images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from difareli.data.store import EncodingStore

_STORES: dict[Path, Path] = {}


@pytest.fixture(scope="session")
def depth_store(synth_store, tmp_path_factory) -> Path:
    """The conftest store (with the depth DiFaReli++ retargeting ray-marches on) plus EXTREMES: s00006_l0 with
    an all-black, an all-white and a saturated (random 0/255) image. Built once per session."""
    if synth_store in _STORES:
        return _STORES[synth_store]
    src = EncodingStore.open(synth_store)
    assert src.available("depth"), "SynthFaces stores carry depth (target shadow maps are ray-marched on it)"
    dst = EncodingStore.create(tmp_path_factory.mktemp("relight") / "store", src.dims, src.encodings, src.store_meta)
    for rid in src.ids():
        dst.write(rid, {k: np.asarray(v) for k, v in src.read(rid).items()}, src.meta(rid))
    base = {k: np.asarray(v) for k, v in dst.read("s00006_l0").items()}
    rng = np.random.default_rng(0)
    images = {"x_black": np.zeros_like(base["image"]), "x_white": np.full_like(base["image"], 255),
              "x_saturated": (rng.integers(0, 2, base["image"].shape) * 255).astype(np.uint8)}
    for rid, image in images.items():
        dst.write(rid, {**base, "image": image}, {**src.meta("s00006_l0"), "subject": "extreme"})
    _STORES[synth_store] = dst.root
    return dst.root
