"""The benchmark's relights made in batches (issue 63): several pairs per network pass through a method's
``relight_many`` (:meth:`difareli.evaluation.baselines.DiffusionMethod.relight_many`, the relighter's one decode
loop), handed to :meth:`difareli.evaluation.benchmark.BenchmarkJob.run`'s pair loop, which checks and scores each as
it would the method's own relight of that pair. A method without ``relight_many`` relights pair by pair."""

from __future__ import annotations

import time
from typing import NamedTuple, Sequence

import numpy as np

from difareli import errors
from difareli.data.store import CorruptRecordError, EncodingStore
from difareli.evaluation.baselines import Method
from difareli.evaluation.pairs import Lights, Pair, StoredFace


class Made(NamedTuple):
    """A pair relit in a batch: its image, its share of the call's seconds, and its source as the call read and
    checked it (the pair loop scores from it instead of reading the record again)."""

    relit: np.ndarray
    seconds: float
    source: StoredFace


class BatchedRelights:
    """The relights of a run's pairs still to score, made through the method's ``relight_many`` (where it has one)
    when the loop first asks for one of them: each source with the targets of all its pairs (both protocols': one
    inversion per source, as the relighter's cache gives one pair at a time), sources of as many targets K a call,
    ``method.batch_size // K`` of them (at least one). A call that fails on a bad record or a non-finite result
    leaves its pairs to the pair by pair path, which fails only the bad pair's row. A pair's seconds: its call's
    time over the call's pairs."""

    def __init__(self, store: EncodingStore, method: Method, lights: Lights, oracle_shadow: bool,
                 todo: Sequence[tuple[str, Pair]]):
        self.store, self.method, self.lights, self.oracle_shadow = store, method, lights, oracle_shadow
        self.ready: dict[tuple[str, str], Made] = {}
        self.calls: list[list[tuple[str, list[tuple[str, Pair]]]]] = []
        self.call_of: dict[tuple[str, str], int] = {}
        self.made: set[int] = set()
        if not hasattr(method, "relight_many"):
            return
        by_source: dict[str, list[tuple[str, Pair]]] = {}
        for short, pair in todo:
            by_source.setdefault(pair.source, []).append((short, pair))
        by_k: dict[int, list[tuple[str, list[tuple[str, Pair]]]]] = {}
        for sid, pairs in by_source.items():  # relight_many takes as many targets for every source
            by_k.setdefault(len(pairs), []).append((sid, pairs))
        batch = max(1, int(getattr(method, "batch_size", 1)))
        for k, group in by_k.items():
            # At most batch_size relights a decode: a tiny 64 px pass cost 15.6 ms per image at batch 96 against 9.7
            # at 16 and 13.2 at 1 (bf16, one thread, quiet 2-core EPYC), so 16 sources x 6 targets lost the gain.
            size = max(1, batch // k)
            for first in range(0, len(group), size):
                self.calls.append(group[first:first + size])
                for _, pairs in self.calls[-1]:
                    self.call_of.update({(short, pair.id): len(self.calls) - 1 for short, pair in pairs})

    def get(self, short: str, pair: Pair) -> Made | None:
        """A pair's :class:`Made`, its call made now if it was not yet; None (a pair resumed, or left to the pair by
        pair path): relight it on its own."""
        key = (short, pair.id)
        call = self.call_of.pop(key, None)
        if call is not None and call not in self.made:  # once: a failed call is not retried pair by pair
            self.made.add(call)
            self._make(self.calls[call])
        return self.ready.pop(key, None)

    def _make(self, call: list[tuple[str, list[tuple[str, Pair]]]]) -> None:
        faces = [StoredFace(self.store, sid) for sid, _ in call]
        targets = [[(*self.lights.for_pair(p, oracle_shadow=self.oracle_shadow), self.lights.sun(p))
                    for _, p in pairs] for _, pairs in call]
        start = time.perf_counter()
        try:
            for face in faces:
                errors.check_record(face.read(), face.id, self.store.root)
            images = self.method.relight_many(faces, targets)
        except (errors.NonFiniteError, CorruptRecordError):
            return  # each pair of the call relit on its own: only a bad one fails
        seconds = (time.perf_counter() - start) / sum(len(pairs) for _, pairs in call)
        for (_, pairs), relit, face in zip(call, images, faces):
            self.ready.update({(short, p.id): Made(image, seconds, face) for (short, p), image in zip(pairs, relit)})
