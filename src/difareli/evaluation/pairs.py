"""A benchmark's evaluation pairs and their lights: the store's ``protocols.json`` as :class:`Pair` s,
:class:`StoredFace` (one record of a pair, the input or the ground truth, as a
:class:`~difareli.evaluation.baselines.Method` is given it) and :class:`Lights` (a pair's target light and shadow
strength, and the fitted lights' errors)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from difareli import errors
from difareli.data.protocols import PROTOCOLS, PROTOCOLS_FILE, SPLITS_FILE
from difareli.data.store import EncodingStore
from difareli.data.target_shadow import target_shadow_of
from difareli.lighting import sh
from difareli.lighting.light_fit import LightFit
from difareli.render import sun_fit
from difareli.utils.fileio import read_json_mapping


@dataclass(frozen=True)
class Pair:
    """One protocol pair: relight ``source`` with the light of ``light_source``; ground truth ``target``."""

    protocol: str
    source: str
    light_source: str
    target: str

    @property
    def id(self) -> str:
        # (source, light source) is unique within a protocol; the target follows from them.
        return f"{self.source}__{self.light_source}"


class StoredFace:
    """One record of a store, as a relighting method is given it: its ``store`` and ``id``, and its encodings
    (:meth:`read`, :attr:`image`), each read from the store once however often the benchmark and the method ask."""

    def __init__(self, store: EncodingStore, record_id: str):
        self.store, self.id = store, str(record_id)
        self._arrays: dict[str, np.ndarray] = {}

    def read(self, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """The record's ``names`` encodings (None: every one the store declares), read-only as the store gives them."""
        names = list(self.store.encodings if names is None else names)
        missing = [n for n in names if n not in self._arrays]
        if missing:
            self._arrays.update(self.store.read(self.id, missing))
        return {n: self._arrays[n] for n in names}

    @property
    def image(self) -> np.ndarray:
        """The record's uint8 HxWx3 image (read-only)."""
        return self.read(["image"])["image"]

    def __repr__(self) -> str:
        return f"StoredFace({self.id!r} of {self.store.root})"


def protocols_doc(store: EncodingStore) -> dict:
    """The store's ``protocols.json`` (written by difareli-synth or difareli-multipie)."""
    path = Path(store.root) / PROTOCOLS_FILE
    if not path.is_file():
        raise errors.UserFileNotFoundError(f"{path} missing: benchmarks need a store with evaluation pairs "
                                           "(difareli-synth or difareli-multipie writes it)")
    try:
        doc = json.loads(path.read_text())
    except (ValueError, RecursionError) as e:  # a JSONDecodeError / RecursionError traceback before
        doc = e
    if not isinstance(doc, dict):
        why = type(doc).__name__ if isinstance(doc, BaseException) else f"a JSON {type(doc).__name__}"
        raise errors.UserError(f"{path} is not the object of pair lists the store's writer made ({why}): corrupt; "
                               "write the store's pairs again (rerun the difareli-synth or difareli-multipie command "
                               "that made it) or restore the file")
    return doc


def no_pairs(path: Path, protocol: str, others: Sequence[str]) -> str:
    """Why ``protocols.json`` at ``path`` lists no ``protocol`` pairs, from the store's ``splits.json`` where it has
    one (an empty test split: a store of fewer than 3 light groups), and the fix."""
    splits = read_json_mapping(path.parent / SPLITS_FILE).get("splits")
    test = splits.get("test") if isinstance(splits, dict) else None
    alone = f", or benchmark the other alone: protocols=[{others[0]}]" if others else ""
    if isinstance(test, list) and not test:
        n = sum(len(v) for v in splits.values() if isinstance(v, list))
        why = (f"its test split is empty ({SPLITS_FILE}: {n} subject(s), all in train or val; a test split needs 3 "
               "or more light groups); make the store with more subjects, e.g. difareli-synth subjects=8 lights=2")
    elif protocol == "same_subject":
        why = "its test subjects have one light each; make the store with lights=2 or more"
    else:
        why = "its test split has no light group of 2 or more subjects; make the store with light_group_size=2 or more"
    return f"{path} has no {protocol} pairs: {why}{alone}"


def load_pairs(store: EncodingStore, protocols: Sequence[str], limit: int | None = None,
               doc: Mapping[str, Any] | None = None) -> dict[str, list[Pair]]:
    """The pairs of each protocol from the store's ``protocols.json`` (``doc``: as :func:`protocols_doc` read it
    already); ``limit`` keeps at most that many, evenly spaced over the list (so a small run still covers several
    subjects and lights)."""
    path = Path(store.root) / PROTOCOLS_FILE
    doc = protocols_doc(store) if doc is None else doc
    out: dict[str, list[Pair]] = {}
    for p in protocols:
        if p not in PROTOCOLS:
            raise errors.UserError(f"unknown protocol {p!r}; choose from {list(PROTOCOLS)}")
        rows = doc.get(p, [])
        if not rows:
            raise errors.UserError(no_pairs(path, p, [q for q in protocols if doc.get(q)]))
        if limit is not None and 0 < limit < len(rows):
            rows = [rows[i] for i in np.unique(np.linspace(0, len(rows) - 1, int(limit)).round().astype(int))]
        out[p] = [Pair(p, r["source"], r["light_source"], r["target"]) for r in rows]
    return out


def exact_light_name(store: EncodingStore) -> str:
    """The encoding holding a record's exact light: ``light_gt`` in SynthFaces v2 stores, else ``light``."""
    return "light_gt" if store.available("light_gt") else "light"


def irradiance_error(estimate: np.ndarray, truth: np.ndarray, normals: np.ndarray,
                     mask: np.ndarray) -> tuple[float, float]:
    """Relative irradiance error ``|E_est - E_gt| / |E_gt|`` over the masked pixels (all channels), and the
    same after the best scalar scale of ``E_est`` (the part an albedo-scale error cannot explain)."""
    n = np.asarray(normals, dtype=np.float64)[mask]
    e, g = sh.irradiance(estimate, n), sh.irradiance(truth, n)
    norm = float(np.linalg.norm(g))
    if norm == 0 or n.size == 0:
        return math.nan, math.nan
    k = float((e * g).sum() / max((e * e).sum(), 1e-30))
    return float(np.linalg.norm(e - g)) / norm, float(np.linalg.norm(k * e - g)) / norm


class Lights:
    """Target (and source) lights per record, estimated once each; errors against the stored light."""

    def __init__(self, store: EncodingStore, estimator: LightFit | None, sun_from_shadows: bool = False):
        self.store, self.estimator, self.sun_from_shadows = store, estimator, sun_from_shadows
        self.shadow_note = ""
        self._cache: dict[str, np.ndarray] = {}
        self._suns: dict[str, np.ndarray | None] = {}

    def get(self, record_id: str) -> np.ndarray:
        """``record_id``'s light: fitted to its image by the estimator, or (none) its exact light."""
        if self.estimator is None:
            name = exact_light_name(self.store)
            return np.asarray(self.store.read(record_id, [name])[name], dtype=np.float64)
        if record_id not in self._cache:
            self._cache[record_id] = self.estimator.from_store(self.store, record_id)
        return self._cache[record_id]

    def for_pair(self, pair: Pair, oracle_shadow: bool = False) -> tuple[np.ndarray, float | None]:
        """``pair``'s target light and shadow strength c: a user's (from the light-source image), or the ground
        truth's exact ones (oracle lights: no estimator; ``oracle_shadow``: the exact c alone)."""
        oracle = self.estimator is None
        light = self.get(pair.target if oracle else pair.light_source)
        return light, self.shadow(pair.target if oracle or oracle_shadow else pair.light_source, oracle=oracle_shadow)

    def sun(self, pair: Pair) -> np.ndarray | None:
        """Where ``pair``'s target map is marched: the fitted light's key sun found from the light-source image's
        cast shadows (``render.sun_fit``, with ``sun_from_shadows``), once per record; None (the light's radiance
        peak) for exact lights or a store without the image, depth, normals or face mask it reads."""
        if self.estimator is None or not self.sun_from_shadows:
            return None
        rid = pair.light_source
        if rid not in self._suns:
            found = sun_fit.record_sun(self.store, rid, self.get(rid), fit=self.estimator)
            self._suns[rid] = None if found is None else found.direction
        return self._suns[rid]

    def shadow(self, record_id: str, oracle: bool = False) -> float | None:
        """The cast-shadow strength c' a user has for the target given by ``record_id``'s image, or the exact
        one (``oracle``, or oracle lights); :func:`~difareli.data.target_shadow.target_shadow_of` states the policy."""
        c, self.shadow_note = target_shadow_of(self.store, record_id, oracle=oracle or self.estimator is None)
        return c

    def errors(self, pair: Pair, light: np.ndarray, source_light: Callable[[StoredFace], np.ndarray] | None = None,
               source: StoredFace | None = None) -> list[dict]:
        """``pair``'s rows of the light-estimation errors (all but the protocol): its target ``light``'s, if
        fitted, and the source light a method fits itself (``source_light``: the method's own door, so the
        light scored is the one it relights with, fitted once; given the pair's ``source`` as the caller read it,
        if any), against the exact lights."""
        out = []
        if self.estimator is not None:
            out.append(("target", pair.light_source, self.error(light, pair.target, pair.target)))
        if source_light is not None:
            fitted = source_light(source or StoredFace(self.store, pair.source))
            out.append(("source", pair.source, self.error(fitted, pair.source, pair.source)))
        return [{"record_id": pair.id, "light": which, "from": frm, "rel_error": rel, "rel_error_gain_free": free}
                for which, frm, (rel, free) in out]

    def error(self, estimate: np.ndarray, truth_id: str, on_id: str) -> tuple[float, float]:
        """:func:`irradiance_error` of ``estimate`` vs ``truth_id``'s light on ``on_id``'s face normals."""
        a = self.store.read(on_id, ["normal", "face_mask"])
        n = np.asarray(a["normal"], dtype=np.float64)
        mask = np.asarray(a["face_mask"], dtype=bool) & (np.linalg.norm(n, axis=-1) > 0.5)
        name = exact_light_name(self.store)
        truth = np.asarray(self.store.read(truth_id, [name])[name], dtype=np.float64)
        return irradiance_error(estimate, truth, n, mask)
