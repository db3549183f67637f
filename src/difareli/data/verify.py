"""Checking a store's records against its header (``EncodingStore.verify``, ``difareli-store verify``).

Every problem is one line naming the record: a missing or unreadable file, a shape or dtype the schema does not
want, a derived version of the wrong shape, or a ``meta.json`` without the keys readers select records by. Only
``.npy`` headers are read unless ``check_values``, which also loads every array and checks its values.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from difareli.data import encodings as enc
from difareli.data.records import META
from difareli.errors import check_light


def problems(store: Any, ids: Iterable[str] | None = None, *, check_values: bool = False) -> list[str]:
    """Problems of ``ids`` (default: every record) of an :class:`~difareli.data.store.EncodingStore`, empty if
    healthy; ``check_values`` also loads every array and checks finiteness (and lights as relight does)."""
    out = []
    splits_used = _splits_used(store)  # once: whether every record must name its split
    for rid in store.ids() if ids is None else ids:
        path = store.records_dir / rid
        if not path.is_dir():
            out.append(f"{rid}: record folder missing")
            continue
        out += _meta_problems(store, rid, path / META, splits_used)
        for name in store.encodings:
            file = path / f"{name}.npy"
            if not file.is_file():
                out.append(f"{rid}: missing encoding {name!r} ({file.name})")
                continue
            try:
                arr = np.load(file, mmap_mode="r", allow_pickle=False)
                want = enc.get(name).resolve(store.dims)
                if arr.shape != want or arr.dtype != np.dtype(enc.get(name).dtype):
                    out.append(f"{rid}: {name} has shape {arr.shape} {arr.dtype}, schema wants {want} "
                               f"{enc.get(name).dtype}")
                elif check_values:
                    enc.get(name).validate(np.asarray(arr), store.dims)
                    if name.startswith("light"):  # what every relight checks (errors.check_light)
                        check_light(np.asarray(arr), f"{name}")
            except (OSError, ValueError, EOFError) as e:  # EOFError: an empty (truncated) file
                out.append(f"{rid}: {name} unreadable ({type(e).__name__}: {e})")
        for derived in store.derived:  # a derived version may cover one split; where present it must be whole
            file = path / f"{derived}.npy"
            base = derived.partition("@")[0]
            if file.is_file() and base in enc.ENCODINGS:
                try:
                    arr = np.load(file, mmap_mode="r", allow_pickle=False)
                    if arr.shape != enc.get(base).resolve(store.dims):
                        out.append(f"{rid}: derived {derived} has shape {arr.shape}, schema wants "
                                   f"{enc.get(base).resolve(store.dims)}")
                except (OSError, ValueError, EOFError) as e:
                    out.append(f"{rid}: derived {derived} unreadable ({type(e).__name__}: {e})")
    return out


def _splits_used(store: Any) -> bool:
    """Whether any record of the store names its split (then every record must)."""
    for rid in store.ids():
        try:
            if "split" in json.loads((store.records_dir / rid / META).read_text()):
                return True
        except (OSError, ValueError, TypeError):
            continue
        return False  # the first readable record decides (records of one store are written alike)
    return False


def _meta_problems(store: Any, rid: str, path: Path, splits_used: bool) -> list[str]:
    """Problems of one record's meta: unreadable, not an object, or without the keys readers select by."""
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        return [f"{rid}: {META} unreadable ({type(e).__name__}: {e})"]
    if not isinstance(meta, dict):
        return [f"{rid}: {META} holds {type(meta).__name__}, not an object"]
    synth = store.store_meta.get("generator") == "synthfaces"
    need = (["split", "subject", "light_index"] if synth else []) + (["split"] if splits_used else [])
    need = list(dict.fromkeys(need))
    missing = [k for k in need if k not in meta]
    return [f"{rid}: {META} lacks {missing} (the record drops out of every split and protocol)"] if missing else []
