"""EncodingStore: one on-disk store of per-image encodings (docs/architecture.md, "Store layout").

Layout::

    <root>/store.json                           {"schema_version", "dims", "encodings", "meta"}
    <root>/records/<record_id>/<encoding>.npy   one file per encoding, read with np.load(mmap_mode="r")
    <root>/records/<record_id>/meta.json        per-record metadata (split, subject, source, ...)

Writes are atomic per record (:mod:`difareli.data.records`: a scratch folder renamed into place), so a killed
run never leaves a partial record and a rerun resumes by skipping what exists. Reads are lazy: only the requested
encodings are opened, as read-only memmaps. :mod:`difareli.data.verify` checks the records against the header.
Torch-free on purpose (numpy + json only) so DataLoader workers and CLI tools import it cheaply.
"""

from __future__ import annotations

import bisect
import json
import os
import warnings
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from difareli.utils.fileio import fsync_dir, write_text_atomic
from difareli.data import encodings as enc
from difareli.data import records
# validate_record_id, META and RECORDS are also named from here (tests, readers of the layout).
from difareli.data.records import META, RECORDS, is_record_id, validate_record_id
from difareli.data.verify import problems as verify_problems
from difareli.errors import MissingError, UserError, UserFileNotFoundError

HEADER = "store.json"
#: Schema versions this code reads. v2 only appended encodings (SynthFaces v2's ``*_gt`` block) and changed none,
#: so a v1 store reads unchanged (it simply lacks the v2 encodings; ``available`` says so).
READABLE_VERSIONS = (1, enc.SCHEMA_VERSION)


class CorruptRecordError(UserError):
    """One record's stored file is unreadable or of the wrong shape or kind: that record is bad, not the store
    (the benchmark scores such a pair as a failed row)."""


class EncodingStore:
    """A folder of per-image encoding records with a header; see the module docstring for the layout."""

    def __init__(self, root: str | os.PathLike, header: Mapping[str, Any], *, durable: bool = True):
        # Use EncodingStore.create / EncodingStore.open; this only binds an already validated header.
        self.root = Path(root)
        self.schema_version = int(header["schema_version"])
        self.dims: dict[str, int] = {k: int(v) for k, v in header["dims"].items()}
        self.encodings: tuple[str, ...] = tuple(header["encodings"])
        self.store_meta: dict[str, Any] = dict(header.get("meta", {}))
        #: derived encoding versions ``base@version`` -> provenance (difareli.data.derived), and the ones a reader uses
        self.derived: dict[str, Any] = dict(header.get("derived", {}))
        self.versions: dict[str, str] = {}
        #: fsync each file and folder on write; False trades crash durability for speed (tests, scratch).
        self.durable = durable
        self._ids: list[str] | None = None
        self._index: dict[str, dict[str, Any]] | None = None

    # ------------------------------------------------------------------ creation / opening
    @classmethod
    def create(
        cls,
        root: str | os.PathLike,
        dims: Mapping[str, int],
        encodings: Iterable[str],
        meta: Mapping[str, Any] | None = None,
        *,
        durable: bool = True,
    ) -> "EncodingStore":
        """Create a store, or reopen an existing one with the same dims and encodings (resume) for writing."""
        root = Path(root)
        names = list(dict.fromkeys(encodings))
        if not names:
            raise UserError("a store needs at least one encoding")
        for name in names:
            enc.get(name)  # raises listing the valid names
        dims = {str(k): int(v) for k, v in dims.items()}
        for k, v in dims.items():
            if v <= 0:
                raise UserError(f"store dimension {k}={v} must be positive")
        for name in names:
            try:
                enc.get(name).resolve(dims)
            except KeyError as e:
                raise UserError(e.args[0]) from None
        header = {"schema_version": enc.SCHEMA_VERSION, "dims": dims, "encodings": names, "meta": dict(meta or {})}
        if (root / HEADER).exists():
            store = cls.open(root, writable=True, durable=durable)
            if store.dims != dims:
                diff = {k: (store.dims.get(k), dims.get(k)) for k in sorted(set(store.dims) | set(dims))
                        if store.dims.get(k) != dims.get(k)}
                raise UserError(
                    f"store {root} exists with dims {store.dims}, requested {dims}; differing dims "
                    f"(existing, requested): {diff}. Use a new root or delete the old store."
                )
            if list(store.encodings) != names:
                raise UserError(
                    f"store {root} exists with encodings {list(store.encodings)}, requested {names}. "
                    "Use a new root or delete the old store."
                )
            if meta is not None and dict(meta) != store.store_meta:
                warnings.warn(f"store {root} exists with different meta; keeping the existing header", stacklevel=2)
            return store
        (root / RECORDS).mkdir(parents=True, exist_ok=True)
        write_text_atomic(root / HEADER, json.dumps(header, indent=2, sort_keys=True) + "\n")  # full disk: one line
        fsync_dir(root)
        return cls(root, header, durable=durable)

    @classmethod
    def open(cls, root: str | os.PathLike, *, writable: bool = False, durable: bool = True) -> "EncodingStore":
        """Open an existing store; ``writable=True`` also clears scratch folders left by killed writers."""
        root = Path(root)
        path = root / HEADER
        if not path.is_file():
            raise UserFileNotFoundError(f"no encoding store at {root} (missing {HEADER}); make one with "
                                        "difareli-synth, difareli-preprocess or difareli-teacher-pairs")
        try:
            header = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise UserError(f"corrupt store header {path}: {e}") from None
        missing = {"schema_version", "dims", "encodings"} - set(header)
        if missing:
            raise UserError(f"store header {path} lacks {sorted(missing)}")
        version = int(header["schema_version"])
        if version not in READABLE_VERSIONS:
            raise UserError(
                f"store {root} has schema_version {header['schema_version']} but this code reads versions "
                f"{list(READABLE_VERSIONS)} (it writes version {enc.SCHEMA_VERSION}, "
                "difareli.data.encodings.SCHEMA_VERSION); "
                "regenerate the store with this code, or use the code version that wrote it"
            )
        store = cls(root, header, durable=durable)
        if writable:  # a reader creates nothing: a store may sit on a read-only disk, or lack an empty records/
            (root / RECORDS).mkdir(exist_ok=True)
            store.clean_scratch()
        return store

    def clean_scratch(self) -> list[str]:
        """Remove ``.tmp-*`` folders of dead writers; restore records whose overwrite was interrupted."""
        removed = records.clean_scratch(self.records_dir)
        if removed:
            self.refresh()
        return removed

    # ------------------------------------------------------------------ properties
    @property
    def records_dir(self) -> Path:
        """Folder holding one sub-folder per completed record."""
        return self.root / RECORDS

    def available(self, name: str) -> bool:
        """Whether encoding ``name`` is declared in the header (i.e. every record has it)."""
        return name in self.encodings

    def use_versions(self, versions: Mapping[str, str | None] | None) -> "EncodingStore":
        """Read these derived versions in place of their base encodings (``{"shadow_map": "diff-1a2b"}``;
        a None version keeps the base); returns the store. Unknown versions are refused, listing the declared."""
        chosen = {}
        for base, version in dict(versions or {}).items():
            if version is None:
                continue
            name = f"{base}@{version}"
            if name not in self.derived:
                have = sorted(self.derived) or "none"
                raise UserError(f"versions.{base}={version!r}: store {self.root} has no {name} (derived versions: "
                                f"{have}); compute it (difareli-shadow-maps) or drop the key")
            chosen[base] = str(version)
        self.versions = chosen
        return self

    def __repr__(self) -> str:
        return f"EncodingStore({str(self.root)!r}, dims={self.dims}, encodings={list(self.encodings)})"

    # ------------------------------------------------------------------ writing
    def write(
        self,
        record_id: str,
        arrays: Mapping[str, np.ndarray],
        meta: Mapping[str, Any] | None = None,
        *,
        overwrite: bool = False,
    ) -> bool:
        """Write one record atomically; returns False (and writes nothing) if it exists and not ``overwrite``.

        ``arrays`` must hold exactly the header's encodings, each valid for the schema and the store's dims.
        """
        validate_record_id(record_id)
        if (self.records_dir / record_id).exists() and not overwrite:
            return False
        checked = self._validate_arrays(record_id, arrays)
        meta_text = records.dump_meta(record_id, meta)
        self.records_dir.mkdir(exist_ok=True)  # opened to read, then written to
        written = records.write_atomic(self.records_dir, record_id, checked, meta_text, overwrite=overwrite,
                                       durable=self.durable)
        if written:
            if self._ids is not None and record_id not in self._ids:
                bisect.insort(self._ids, record_id)
            if self._index is not None:
                self._index[record_id] = json.loads(meta_text)
        return written

    def _validate_arrays(self, record_id: str, arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        unknown = [n for n in arrays if n not in self.encodings]
        if unknown:
            raise UserError(
                f"record {record_id!r}: encodings {unknown} are not declared in the header of {self.root} "
                f"(declared: {list(self.encodings)})"
            )
        missing = [n for n in self.encodings if n not in arrays]
        if missing:
            raise UserError(f"record {record_id!r}: missing encodings {missing} declared in the header of {self.root}")
        out = {}
        for name in self.encodings:
            try:
                out[name] = np.ascontiguousarray(enc.get(name).validate(arrays[name], self.dims))
            except ValueError as e:
                raise UserError(f"record {record_id!r}: {e}") from None
        return out

    # ------------------------------------------------------------------ reading
    def has(self, record_id: str) -> bool:
        """Whether a completed record with this id exists."""
        validate_record_id(record_id)
        return (self.records_dir / record_id).is_dir()

    def __contains__(self, record_id: object) -> bool:
        return is_record_id(record_id) and self.has(record_id)

    def refresh(self) -> None:
        """Forget the cached listing and index (after other processes wrote records)."""
        self._ids = None
        self._index = None

    def _all_ids(self) -> list[str]:
        if self._ids is None:
            # One scandir for the whole store; names starting with '.' are scratch folders, never records.
            self._ids = sorted(e.name for e in os.scandir(self.records_dir)
                               if not e.name.startswith(".") and e.is_dir()) if self.records_dir.is_dir() else []
        return self._ids

    @property
    def index(self) -> dict[str, dict[str, Any]]:
        """Per-record meta for every record, read once (O(N)) and cached; used to filter by split/subject."""
        if self._index is None:
            index = {rid: self.meta(rid) for rid in self._all_ids()}
            lost = [rid for rid, m in index.items() if "split" not in m]
            if lost and len(lost) < len(index):  # they would drop out of every split without a word
                raise UserError(f"store {self.root}: {len(lost)} record(s) (e.g. {lost[:3]}) have no 'split' in their "
                                f"{META} while {len(index) - len(lost)} do; regenerate or remove them "
                                f"(difareli-store verify {self.root} lists all)")
            self._index = index
        return self._index

    def ids(self, split: str | None = None, subject: str | None = None) -> list[str]:
        """Sorted ids of completed records, optionally only those whose meta has this split / subject."""
        if split is None and subject is None:
            return list(self._all_ids())
        index = self.index
        return [
            rid for rid in self._all_ids()
            if (split is None or index[rid].get("split") == split)
            and (subject is None or index[rid].get("subject") == subject)
        ]

    def __len__(self) -> int:
        return len(self._all_ids())

    def __iter__(self):
        return iter(self.ids())

    def _record_dir(self, record_id: str) -> Path:
        validate_record_id(record_id)
        path = self.records_dir / record_id
        if not path.is_dir():
            raise MissingError(f"no record {record_id!r} in store {self.root}")
        return path

    def read(self, record_id: str, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """Read-only memmaps of the requested encodings (all declared ones if ``names`` is None)."""
        path = self._record_dir(record_id)
        names = self.encodings if names is None else list(names)
        out = {}
        for name in names:
            base = name.partition("@")[0]  # an explicit derived version reads as its base encoding
            enc.get(base)
            stem = f"{name}@{self.versions[name]}" if name in self.versions else name  # a chosen derived version
            file = path / f"{stem}.npy"
            try:
                out[name] = np.load(file, mmap_mode="r", allow_pickle=False)
            except FileNotFoundError:
                if stem != name or "@" in name:
                    raise MissingError(f"record {record_id!r} of store {self.root} has no derived {stem!r} yet (a run "
                                       "computing it did not reach it); resume that run or choose another "
                                       "version") from None
                declared = "declared in the header" if self.available(name) else "not in the header either"
                raise MissingError(
                    f"encoding {name!r} missing for record {record_id!r} in store {self.root} ({declared}; "
                    f"available: {list(self.encodings)})"
                ) from None
            except (ValueError, OSError, EOFError) as e:  # truncated / corrupt .npy: name the file, not mmap
                raise CorruptRecordError(f"record {record_id!r}, encoding {name!r} in store {self.root}: {file} "
                                         f"is corrupt or truncated ({str(e)[:100]}); regenerate or remove the "
                                         "record") from None
            if self.available(base) and out[name].shape != enc.get(base).resolve(self.dims):
                raise CorruptRecordError(f"record {record_id!r}, encoding {name!r} in store {self.root} has "
                                         f"shape {out[name].shape}, the store's schema wants "
                                         f"{enc.get(base).resolve(self.dims)}; regenerate or remove the record")
        return out

    def meta(self, record_id: str) -> dict[str, Any]:
        """The record's metadata dict."""
        path = self._record_dir(record_id) / META
        try:
            meta = json.loads(path.read_text())
        except FileNotFoundError:
            raise MissingError(f"record {record_id!r} in store {self.root} has no {META}") from None
        except ValueError as e:
            raise CorruptRecordError(f"record {record_id!r} in store {self.root}: {META} is not JSON ({e}); "
                                     f"regenerate or remove the record (difareli-store verify {self.root} lists "
                                     "all)") from None
        if not isinstance(meta, dict):
            raise CorruptRecordError(f"record {record_id!r} in store {self.root}: {META} holds "
                                     f"{type(meta).__name__}, not an object; regenerate or remove the record")
        return meta

    def verify(self, ids: Iterable[str] | None = None, *, check_values: bool = False) -> list[str]:
        """Problems found (empty if healthy): missing/unreadable files, wrong shapes or dtypes, bad meta
        (:func:`difareli.data.verify.problems`). Only headers are read unless ``check_values``, which also loads
        every array and checks finiteness."""
        self.refresh()
        return verify_problems(self, ids, check_values=check_values)
