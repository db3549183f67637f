"""The two Multi-PIE evaluation protocols: read from the authors' JSON lists, or drawn from a seed.

A pair relights ``source`` with the light estimated from ``light_source`` and scores it against ``target``, the
source's own sitting under the light source's illumination:

- (i) ``same_subject``: the light comes from the same person (the authors' "mp_test" list; when drawn here,
  ``light_source`` is the target itself, as in SynthFaces' protocol (i) and Hou et al.'s test set);
- (ii) ``different_subject``: the light comes from another person under the same illumination id ("mp_test2").

The authors' lists are JSON objects ``{"pair": {"pair1": {"src": ..., "dst": ..., "gt": ...}, ...}}`` of file names
(``001_01_01_051_07.png``); a bare ``{"pair1": {...}}`` object or a list of such entries is read too, and a missing
``gt`` is the source's sitting under ``dst``'s illumination. Which protocol a pair belongs to follows from the
subjects of ``src`` and ``dst``, so both lists may be given at once in any order.

Drawn protocols (:func:`draw`), from ``seed`` alone and the images found: sittings are visited in a seeded order,
round-robin, each giving its next unused (source illumination i, target illumination j != i) per round until the
requested count is reached or nothing is left. (ii) adds, for each such (sitting, i, j), a light source drawn from
the other subjects' images under illumination j.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from difareli.data.protocols import PROTOCOLS
from difareli.errors import UserError
from difareli.multipie.layout import Image



@dataclass(frozen=True)
class Triple:
    """One evaluation pair: relight ``source`` with ``light_source``'s light; ground truth ``target``."""

    source: Image
    light_source: Image
    target: Image
    origin: str = ""  # where it came from: "<file> <pair key>" or "drawn"

    @property
    def protocol(self) -> str:
        return "same_subject" if self.source.subject == self.light_source.subject else "different_subject"

    @property
    def images(self) -> tuple[Image, Image, Image]:
        return self.source, self.light_source, self.target

    def as_dict(self) -> dict[str, str]:
        """The ``protocols.json`` entry (record ids are the file stems)."""
        return {"source": self.source.stem, "light_source": self.light_source.stem, "target": self.target.stem}


def _entries(doc, path: Path) -> list[tuple[str, object]]:
    if isinstance(doc, Mapping) and isinstance(doc.get("pair"), Mapping):
        doc = doc["pair"]
    if isinstance(doc, Mapping):
        return [(str(k), v) for k, v in doc.items()]
    if isinstance(doc, list):
        return [(f"entry {i}", v) for i, v in enumerate(doc)]
    raise UserError(f"pairs={path}: a {type(doc).__name__} at the top; expected the authors' "
                    '{"pair": {"pair1": {"src": ..., "dst": ..., "gt": ...}}} layout or a list of such entries')


def read_lists(paths: Iterable[str | Path]) -> list[Triple]:
    """Every pair of the authors' JSON lists at ``paths``; a bad file or entry is a UserError naming it."""
    out: list[Triple] = []
    for path in map(Path, paths):
        if not path.is_file():
            raise UserError(f"pairs={path}: no such file; give the authors' JSON list(s) or pairs=null to draw them")
        try:
            doc = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise UserError(f"pairs={path}: not JSON ({e}); give the authors' list file") from None
        except RecursionError:  # brackets nested thousands deep: a RecursionError traceback before
            raise UserError(f"pairs={path}: nests arrays or objects too deeply to be a pair list; give the authors' "
                            "list file") from None
        entries = _entries(doc, path)
        if not entries:
            raise UserError(f"pairs={path}: no pairs in the file")
        for key, e in entries:
            if not isinstance(e, Mapping) or "src" not in e or "dst" not in e:
                raise UserError(f"pairs={path}: {key} is not an object with 'src' and 'dst' (got {str(e)[:80]})")
            try:
                src, dst = Image.parse(e["src"]), Image.parse(e["dst"])
                gt = Image.parse(e["gt"]) if e.get("gt") else src.under(dst.illumination)
            except ValueError as err:
                raise UserError(f"pairs={path}: {key}: {err}") from None
            if src == dst:  # relit under its own light: the "ground truth" is the input, the score meaningless
                raise UserError(f"pairs={path}: {key}: src and dst are the same image {src.stem}; a pair takes the "
                                "light of another image: fix the list (dst another illumination or subject)")
            if gt.subject != src.subject:
                raise UserError(f"pairs={path}: {key}: gt {gt.stem} shows subject {gt.subject}, the source "
                                f"{src.stem} subject {src.subject}; the ground truth must show the input's person")
            out.append(Triple(src, dst, gt, f"{path.name} {key}"))
    return out


def _round_robin(rng: np.random.Generator, keys: Sequence, options: Mapping, n: int):
    """Yield (key, option) visiting ``keys`` in a seeded order, one unused option per key per round."""
    order = [keys[i] for i in rng.permutation(len(keys))]
    queues = {k: [options[k][i] for i in rng.permutation(len(options[k]))] for k in order}
    given = 0
    while given < n and any(queues.values()):
        for k in order:
            if given >= n:
                return
            if queues[k]:
                yield k, queues[k].pop(0)
                given += 1


def draw(images: Iterable[Image], seed: int = 0, same_subject: int = 862,
         different_subject: int = 200) -> list[Triple]:
    """Both protocols drawn from ``images`` (see the module docstring); the counts are upper bounds."""
    sittings: dict[tuple, dict[str, Image]] = defaultdict(dict)
    by_illum: dict[str, dict[str, list[Image]]] = defaultdict(lambda: defaultdict(list))
    for img in sorted(set(images)):
        sittings[img.recording_key][img.illumination] = img
        by_illum[img.illumination][img.subject].append(img)
    keys = sorted(k for k, v in sittings.items() if len(v) >= 2)
    combos = {k: [(i, j) for i in sorted(sittings[k]) for j in sorted(sittings[k]) if i != j] for k in keys}
    rng = np.random.default_rng([int(seed), 0x4D50])
    out = [Triple(sittings[k][i], sittings[k][j], sittings[k][j], "drawn")
           for k, (i, j) in _round_robin(rng, keys, combos, int(same_subject))]
    # (ii): only (i, j) whose illumination j some other subject has.
    cross = {k: [(i, j) for i, j in combos[k] if any(s != k[0] for s in by_illum[j])] for k in keys}
    cross_keys = [k for k in keys if cross[k]]
    for k, (i, j) in _round_robin(rng, cross_keys, cross, int(different_subject)):
        others = sorted(s for s in by_illum[j] if s != k[0])
        pool = by_illum[j][others[int(rng.integers(len(others)))]]
        out.append(Triple(sittings[k][i], pool[int(rng.integers(len(pool)))], sittings[k][j], "drawn"))
    return out


def protocols_doc(triples: Sequence[Triple], how: str) -> dict:
    """The ``protocols.json`` document difareli-benchmark reads (``exact_lights: false``: Multi-PIE has none)."""
    doc = {"dataset": "multipie", "exact_lights": False, "split": "test", "pairs_from": how,
           "fields": {"source": "record relit", "light_source": "record the target light is estimated from",
                      "target": "ground-truth record (the source's sitting under the light source's illumination)"}}
    for p in PROTOCOLS:
        doc[p] = [t.as_dict() for t in triples if t.protocol == p]
    return doc
