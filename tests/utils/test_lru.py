"""The bounded dict behind the app's and a relighter's caches."""

import numpy as np
import pytest

from difareli.data.store import EncodingStore
from difareli.diffusion.relight import SamplerSpec
from difareli.errors import UserError
from difareli.relight.relighter import Relighter
from difareli.utils.lru import LRU


def test_lru_drops_the_least_recently_used():
    c = LRU(2)
    c["a"], c["b"] = 1, 2
    assert c["a"] == 1  # reading makes "a" the newest
    c["c"] = 3
    assert list(c) == ["a", "c"] and c.get("b") is None and c.get("a") == 1
    c["a"] = 4  # rewriting keeps one entry
    assert len(c) == 2 and c["a"] == 4
    with pytest.raises(UserError, match="cache size 0"):
        LRU(0)


def test_relighter_caches_are_bounded_by_cache_size(tiny_checkpoint, synth_store, one_thread):
    """Three sources through a relighter with cache_size=2: the first source's inversion and key sun are gone,
    and asking for it again inverts it anew to the same result."""
    store = EncodingStore.open(synth_store)
    r = Relighter(tiny_checkpoint("difareli_pp"), SamplerSpec(name="ddim", steps=2),
                  runtime={"device": "cpu", "precision": "fp32"}, cache_size=2)
    sources = [r.source(store, rid) for rid in store.ids()[:3]]
    first = r.inversion(sources[0])
    for s in sources:
        r.inversion(s), r.key_sun(s)
    assert list(r._inversions) == [s.key for s in sources[1:]] == list(r._suns)
    again = r.inversion(sources[0])
    assert again is not first
    np.testing.assert_allclose(again.x_T.numpy(), first.x_T.numpy(), rtol=0, atol=1e-6)
    unbounded = Relighter(tiny_checkpoint("difareli_pp"), SamplerSpec(name="ddim", steps=2),
                          runtime={"device": "cpu", "precision": "fp32"})
    for s in sources:
        unbounded.inversion(s)
    assert len(unbounded._inversions) == 3
