"""Training shadow maps of the kind a relight is tested with, written as derived versions of ``shadow_map``.

A relight's target map is made by one maker (:func:`difareli.render.retarget.shadow_maker`: the depth-map march
toward the target light's suns, an SH light's being one toward its radiance peak, times the normalised c). A
DiFaReli++ trained on maps made another way (SynthFaces' mesh rays toward a fitted light: IoU 0.31 with the march
for the same record and light) is tested out of its training distribution, and one trained on maps that disagree
with its images learns to ignore them.
``difareli-shadow-maps maker=march`` writes every record's map with that same maker:

- ``light=exact`` (default): toward the record's exact light with its exact c (``shadow_gt``), where the store has
  them (SynthFaces v2/v3), so the map agrees with the image it is paired with: the suns its header names (key,
  fill, rim; ambient = ``light_gt`` less theirs) weighed by the share of light each takes
  (``render.visible.visible_march``), else the SH ``light_gt``;
- ``light=fitted``: toward the stored (fitted) light with the stored c, as a user's photo would have them.

``maker=visible`` writes the exact upper bound instead: SynthFaces v3's visibly-shadowed mask
(``shadow_visible_gt``) times the normalised exact c (the maps a model cannot get at test time: can this network
learn cast shadows at all?). Either way the version's provenance names the maker and its settings, resumable and
locked like every derived version.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from tqdm.auto import tqdm

from difareli import errors
from difareli.data import derived, encodings
from difareli.data.inputs import read_record
from difareli.lighting.suns import Suns
from difareli.render.retarget import shadow_maker, target_shadow_map
from difareli.utils.fileio import folder_lock

METHODS = ("march", "visible")
LIGHTS = ("exact", "fitted")


@dataclass
class MapsReport:
    name: str         # shadow_map@<version>
    written: int      # maps written in this run (the rest were resumed)
    records: int
    seconds: float
    provenance: dict


def _names(method: str, light: str) -> tuple[str, str]:
    """The (light, c) encodings a record's map is made from."""
    if method == "visible":
        return "", "shadow_gt"
    return ("light_gt", "shadow_gt") if light == "exact" else ("light", "shadow")


def check(store, method: str, light: str) -> None:
    """The method, the light and the encodings they read, checked before any work."""
    if method not in METHODS:
        raise errors.UserError(f"maker={method!r} is not a map maker here; choose {', '.join(METHODS)} (or "
                               "difference, which needs checkpoint=<a DiFaReli>)")
    if light not in LIGHTS:
        raise errors.UserError(f"light={light!r}: choose exact (the record's light_gt and shadow_gt) or fitted")
    light_name, c_name = _names(method, light)
    needs = ["shadow_visible_gt", c_name] if method == "visible" else ["depth", "normal", "cam", light_name, c_name]
    gone = [n for n in needs if not store.available(n)]
    if gone:
        hint = ("a SynthFaces v3 store (difareli-synth)" if method == "visible"
                else "light=fitted, or a SynthFaces store")
        raise errors.UserError(f"maker={method} light={light} reads {needs}, but store {store.root} has no "
                               f"{', '.join(gone)}; use {hint}")


def make_map(arrays, method: str, light: str, c_range, header=None) -> np.ndarray:
    """One record's map (float32 HxW) from its arrays (as :func:`difareli.data.inputs.read_record` gives them);
    ``header``: the record's header (``store.meta``), whose suns the exact light is marched toward."""
    light_name, c_name = _names(method, light)
    c = encodings.shadow_logit(arrays, c_name)
    if method == "visible":
        return (np.asarray(arrays["shadow_visible_gt"], bool) * encodings.normalise_c(c, c_range)).astype(np.float32)
    sh_light = np.asarray(arrays[light_name], dtype=np.float64)
    suns = Suns.from_header(header, sh_light) if light == "exact" and header else None
    return target_shadow_map(arrays, suns if suns is not None else sh_light, c, c_range)


def compute(store, *, method: str = "march", light: str = "exact", version: str | None = None,
            ids: Sequence[str] | None = None, progress: bool = True) -> MapsReport:
    """Write ``shadow_map@<version>`` for ``ids`` (default every record) with ``method``; resumes a killed run."""
    check(store, method, light)
    ids = list(ids) if ids is not None else store.ids()
    c_range = encodings.store_c_range(store.store_meta)
    prov = {"method": method, "light": light, "c_range": list(c_range) if c_range else "fixed"}
    if method == "march":
        prov["maker"] = shadow_maker()
    chosen = "all" if set(ids) == set(store.ids()) else derived.content_version("ids", {"ids": sorted(ids)}, 12)
    version = version or derived.content_version(method, {**prov, "records": chosen})
    with folder_lock(store.root, "shadow-maps"):
        try:
            name = derived.declare(store, "shadow_map", version, {**prov, "records": chosen, "n_records": len(ids)})
        except ValueError as e:
            raise errors.UserError(f"{e} (give another version=)") from None
        light_name, c_name = _names(method, light)
        reads = ["shadow_visible_gt", c_name] if method == "visible" else ["depth", "normal", "cam", light_name, c_name]
        todo = derived.missing(store, name, ids)
        start, written = time.perf_counter(), 0
        for rid in tqdm(todo, desc=f"{method} maps", disable=not progress):
            arrays = read_record(store, rid, reads)
            written += derived.write(store, rid, name, make_map(arrays, method, light, c_range, store.meta(rid)))
    return MapsReport(name, written, len(ids), time.perf_counter() - start, prov)
