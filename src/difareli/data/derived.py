"""Derived encodings: versioned alternatives of a declared encoding, computed after a store was written
(e.g. DiFaReli++'s difference-method shadow maps, ``shadow_map@diff-<hash>``).

Layout: ``records/<record_id>/<base>@<version>.npy`` beside the record's own encodings (nothing is copied),
and the version's provenance (checkpoint, sampler, threshold, ...) under ``"derived"`` in ``store.json``.
Every per-record file is written to a dot-named scratch file in the record folder and renamed into place
(atomic; a rerun skips records that have the version, so a killed run resumes). A derived array is validated
against its base encoding's schema.

A reader chooses which version a model consumes with ``EncodingStore.use_versions({"shadow_map": "diff-..."})``
(the ``versions`` config key of the DataModule, relight and video CLIs): ``read(rid, ["shadow_map"])`` then
returns that version under the base name, so DataModule, Relighter and the metrics code stay unchanged.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from difareli.data import encodings as enc
from difareli.errors import MissingError, UserError
from difareli.utils.fileio import save_npy_atomic, write_text_atomic
from difareli.data.store import HEADER

SEP = "@"
KEY = "derived"


def version_name(base: str, version: str) -> str:
    """``base@version``, checking both parts (a version is 1-64 characters of [A-Za-z0-9_.+=-])."""
    enc.get(base)
    if (not version or len(version) > 64 or not all(ch.isalnum() or ch in "_.+=-" for ch in version)
            or version[0] in ".-"):
        raise UserError(f"derived version {version!r} is invalid: use 1-64 characters from [A-Za-z0-9_.+=-], not "
                        "starting with '.' or '-'")
    return f"{base}{SEP}{version}"


def split_name(name: str) -> tuple[str, str | None]:
    """``("shadow_map", "diff-1a2b")`` for ``shadow_map@diff-1a2b``; ``(name, None)`` for a plain encoding."""
    base, _, version = name.partition(SEP)
    return base, (version or None)


def content_version(prefix: str, provenance: Mapping[str, Any], length: int = 8) -> str:
    """``<prefix>-<hash>``: a version named by the hash of its provenance (same inputs, same version)."""
    text = json.dumps(dict(provenance), sort_keys=True, default=str)
    return f"{prefix}-{hashlib.sha1(text.encode()).hexdigest()[:length]}"


def update_header(store, key: str, value: Any) -> None:
    """Set ``meta[key]`` of a store's header (atomic rename) and of the open ``store``."""
    path = Path(store.root) / HEADER
    header = json.loads(path.read_text())
    header.setdefault("meta", {})[key] = json.loads(json.dumps(value, default=str))
    write_text_atomic(path, json.dumps(header, indent=2, sort_keys=True) + "\n")
    store.store_meta[key] = header["meta"][key]


def replace_base(store, record_id: str, name: str, array: np.ndarray) -> None:
    """Rewrite one record's own encoding ``name`` in place (scratch file, then rename), validated by its schema."""
    final = Path(store.records_dir) / record_id / f"{name}.npy"
    if not final.is_file():
        raise MissingError(f"record {record_id!r} of store {store.root} has no {name}")
    arr = np.ascontiguousarray(enc.get(name).validate(np.asarray(array), store.dims))
    save_npy_atomic(final, arr)


def declare(store, base: str, version: str, provenance: Mapping[str, Any]) -> str:
    """Record a derived version and its provenance in the store header (atomic rename); returns its name.

    Declaring an existing version again with the same provenance is a no-op (a resumed run); with another
    provenance it is refused (a different computation must get a different version)."""
    name = version_name(base, version)
    if base not in store.encodings:
        raise UserError(f"store {store.root} has no encoding {base!r} to derive a version of")
    path = Path(store.root) / HEADER
    header = json.loads(path.read_text())
    derived = dict(header.get(KEY, {}))
    prov = json.loads(json.dumps(dict(provenance), default=str))
    if name in derived:
        if derived[name] != prov:
            raise UserError(f"store {store.root} already has {name} with other provenance {derived[name]}; choose "
                            "another version name")
    else:
        derived[name] = prov
        header[KEY] = derived
        write_text_atomic(path, json.dumps(header, indent=2, sort_keys=True) + "\n")
    store.derived = derived
    return name


def path_of(store, record_id: str, name: str) -> Path:
    return Path(store.records_dir) / record_id / f"{name}.npy"


def has(store, record_id: str, name: str) -> bool:
    """Whether ``record_id`` has the derived encoding ``name`` (``base@version``)."""
    return path_of(store, record_id, name).is_file()


def missing(store, name: str, ids: Iterable[str]) -> list[str]:
    """The records of ``ids`` without ``name`` (what a resumed run still has to compute)."""
    return [rid for rid in ids if not has(store, rid, name)]


def write(store, record_id: str, name: str, array: np.ndarray, *, overwrite: bool = False) -> bool:
    """Write one record's derived encoding atomically; False (nothing written) if present and not ``overwrite``."""
    base, version = split_name(name)
    if version is None or name not in store.derived:
        raise UserError(f"{name!r} is not a declared derived version of store {store.root} (declare it first; "
                        f"declared: {sorted(store.derived)})")
    final = path_of(store, record_id, name)
    if not final.parent.is_dir():
        raise MissingError(f"no record {record_id!r} in store {store.root}")
    if final.exists() and not overwrite:
        return False
    arr = np.ascontiguousarray(enc.get(base).validate(np.asarray(array), store.dims))
    save_npy_atomic(final, arr, durable=store.durable)
    return True
