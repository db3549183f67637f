"""EncodingStore: one on-disk store of per-image encodings (docs/architecture.md, "Store layout").

Layout::

    <root>/store.json                           {"schema_version", "dims", "encodings", "meta"}
    <root>/records/<record_id>/<encoding>.npy   one file per encoding, read with np.load(mmap_mode="r")
    <root>/records/<record_id>/meta.json        per-record metadata (split, subject, source, ...)

Writes are atomic per record: the files go to ``records/.tmp-<record_id>-<pid>/`` and the folder is renamed
into place with one ``os.rename``, so a killed run never leaves a partial record and a rerun resumes by
skipping what exists. Reads are lazy: only the requested encodings are opened, as read-only memmaps.
Torch-free on purpose (numpy + json only) so DataLoader workers and CLI tools import it cheaply.
"""

from __future__ import annotations

import bisect
import json
import os
import re
import shutil
import warnings
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from difareli.utils.fileio import RESUME, fsync_dir, is_no_space, no_space, write_text_atomic
from difareli.data import encodings as enc
from difareli.errors import MissingError, UserError, UserFileNotFoundError, check_light

HEADER = "store.json"
#: Schema versions this code reads. v2 only appended encodings (SynthFaces v2's ``*_gt`` block) and changed none,
#: so a v1 store reads unchanged (it simply lacks the v2 encodings; ``available`` says so).
READABLE_VERSIONS = (1, enc.SCHEMA_VERSION)
RECORDS = "records"
META = "meta.json"
_TMP = ".tmp-"
_OLD = ".old-"
_ID_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+=-]{0,199}$")


class CorruptRecordError(UserError):
    """One record's stored file is unreadable or of the wrong shape or kind: that record is bad, not the store
    (the benchmark scores such a pair as a failed row)."""


def validate_record_id(record_id: str) -> str:
    """Return ``record_id`` if it is a safe folder name, else raise ValueError saying why."""
    if not isinstance(record_id, str) or not _ID_RE.match(record_id):
        raise UserError(
            f"invalid record id {record_id!r}: use 1-200 characters from [A-Za-z0-9_.+=-], "
            "not starting with '.' or '-' (no '/', no spaces)"
        )
    return record_id


def _json_default(obj: Any) -> Any:
    # numpy scalars/arrays sneak into meta from generators; store them as plain JSON values.
    if isinstance(obj, (np.generic, np.ndarray)):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # our own leftovers (e.g. from a failed write) are stale too
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _split_scratch(name: str) -> tuple[str, str, int] | None:
    """Parse ``.tmp-<id>-<pid>`` / ``.old-<id>-<pid>`` into (kind, id, pid)."""
    for prefix in (_TMP, _OLD):
        if name.startswith(prefix):
            rid, _, pid = name[len(prefix):].rpartition("-")
            if rid and pid.isdigit():
                return prefix, rid, int(pid)
    return None


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
                f"{list(READABLE_VERSIONS)} (it writes version {enc.SCHEMA_VERSION}, difareli.data.encodings.SCHEMA_VERSION); "
                "regenerate the store with this code, or use the code version that wrote it"
            )
        store = cls(root, header, durable=durable)
        (root / RECORDS).mkdir(exist_ok=True)
        if writable:
            store.clean_scratch()
        return store

    def clean_scratch(self) -> list[str]:
        """Remove ``.tmp-*`` folders of dead writers; restore records whose overwrite was interrupted."""
        removed = []
        for entry in os.scandir(self.records_dir):
            parsed = _split_scratch(entry.name)
            if parsed is None or _pid_alive(parsed[2]):
                continue  # a live writer (another process on this host) still owns it
            kind, rid, _ = parsed
            final = self.records_dir / rid
            if kind == _OLD and not final.exists():
                # Killed between "rename old away" and "rename new in": the old record is still whole.
                os.rename(entry.path, final)
            else:
                shutil.rmtree(entry.path, ignore_errors=True)
            removed.append(entry.name)
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
        final = self.records_dir / record_id
        if final.exists() and not overwrite:
            return False
        checked = self._validate_arrays(record_id, arrays)
        try:
            meta_text = json.dumps(dict(meta or {}), indent=1, sort_keys=True, default=_json_default)
        except TypeError as e:
            raise UserError(f"record {record_id!r}: meta is not JSON-serialisable: {e}") from None

        tmp = self.records_dir / f"{_TMP}{record_id}-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        file = final
        try:
            tmp.mkdir()
            for name, arr in checked.items():
                file = final / f"{name}.npy"
                with open(tmp / file.name, "wb") as f:
                    np.save(f, arr, allow_pickle=False)
                    self._sync(f)
            file = final / META
            with open(tmp / META, "w") as f:
                f.write(meta_text + "\n")
                self._sync(f)
            if self.durable:
                fsync_dir(tmp)
            written = self._commit(tmp, final, overwrite)
        except BaseException as e:
            shutil.rmtree(tmp, ignore_errors=True)  # a full disk or a kill leaves no partial record
            if is_no_space(e):
                raise no_space(file, e, RESUME) from None
            raise
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

    def _sync(self, f) -> None:
        if self.durable:
            f.flush()
            os.fsync(f.fileno())

    def _commit(self, tmp: Path, final: Path, overwrite: bool) -> bool:
        old = None
        if final.exists():
            if not overwrite:
                shutil.rmtree(tmp)  # another writer finished it meanwhile
                return False
            old = self.records_dir / f"{_OLD}{final.name}-{os.getpid()}"
            os.rename(final, old)
        try:
            os.rename(tmp, final)
        except OSError:
            if old is not None:
                os.rename(old, final)
                raise
            if final.exists():  # lost a race with a concurrent writer of the same id: theirs stands
                shutil.rmtree(tmp, ignore_errors=True)
                return False
            raise
        if self.durable:
            fsync_dir(self.records_dir)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return True

    # ------------------------------------------------------------------ reading
    def has(self, record_id: str) -> bool:
        """Whether a completed record with this id exists."""
        validate_record_id(record_id)
        return (self.records_dir / record_id).is_dir()

    def __contains__(self, record_id: object) -> bool:
        return isinstance(record_id, str) and _ID_RE.match(record_id) is not None and self.has(record_id)

    def refresh(self) -> None:
        """Forget the cached listing and index (after other processes wrote records)."""
        self._ids = None
        self._index = None

    def _all_ids(self) -> list[str]:
        if self._ids is None:
            # One scandir for the whole store; names starting with '.' are scratch folders, never records.
            self._ids = sorted(e.name for e in os.scandir(self.records_dir) if not e.name.startswith(".") and e.is_dir())
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
                                       "computing it did not reach it); resume that run or choose another version") from None
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
        """Problems found (empty if healthy): missing/unreadable files, wrong shapes or dtypes, bad meta.

        Only headers are read by default; ``check_values`` also loads every array and checks finiteness.
        """
        problems = []
        self.refresh()
        splits_used = self._splits_used()  # once: whether every record must name its split
        for rid in self.ids() if ids is None else ids:
            path = self.records_dir / rid
            if not path.is_dir():
                problems.append(f"{rid}: record folder missing")
                continue
            problems += self._verify_meta(rid, path / META, splits_used)
            for name in self.encodings:
                file = path / f"{name}.npy"
                if not file.is_file():
                    problems.append(f"{rid}: missing encoding {name!r} ({file.name})")
                    continue
                try:
                    arr = np.load(file, mmap_mode="r", allow_pickle=False)
                    want = enc.get(name).resolve(self.dims)
                    if arr.shape != want or arr.dtype != np.dtype(enc.get(name).dtype):
                        problems.append(f"{rid}: {name} has shape {arr.shape} {arr.dtype}, schema wants {want} "
                                        f"{enc.get(name).dtype}")
                    elif check_values:
                        enc.get(name).validate(np.asarray(arr), self.dims)
                        if name.startswith("light"):  # what every relight checks (errors.check_light)
                            check_light(np.asarray(arr), f"{name}")
                except (OSError, ValueError, EOFError) as e:  # EOFError: an empty (truncated) file
                    problems.append(f"{rid}: {name} unreadable ({type(e).__name__}: {e})")
            for derived in self.derived:  # a derived version may cover one split; where present it must be whole
                file = path / f"{derived}.npy"
                base = derived.partition("@")[0]
                if file.is_file() and base in enc.ENCODINGS:
                    try:
                        arr = np.load(file, mmap_mode="r", allow_pickle=False)
                        if arr.shape != enc.get(base).resolve(self.dims):
                            problems.append(f"{rid}: derived {derived} has shape {arr.shape}, schema wants "
                                            f"{enc.get(base).resolve(self.dims)}")
                    except (OSError, ValueError, EOFError) as e:
                        problems.append(f"{rid}: derived {derived} unreadable ({type(e).__name__}: {e})")
        return problems

    def _splits_used(self) -> bool:
        """Whether any record of the store names its split (then every record must)."""
        for rid in self._all_ids():
            try:
                if "split" in json.loads((self.records_dir / rid / META).read_text()):
                    return True
            except (OSError, ValueError, TypeError):
                continue
            return False  # the first readable record decides (records of one store are written alike)
        return False

    def _verify_meta(self, rid: str, path: Path, splits_used: bool) -> list[str]:
        """Problems of one record's meta: unreadable, not an object, or without the keys readers select by."""
        try:
            meta = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            return [f"{rid}: {META} unreadable ({type(e).__name__}: {e})"]
        if not isinstance(meta, dict):
            return [f"{rid}: {META} holds {type(meta).__name__}, not an object"]
        synth = self.store_meta.get("generator") == "synthfaces"
        need = (["split", "subject", "light_index"] if synth else []) + (["split"] if splits_used else [])
        need = list(dict.fromkeys(need))
        missing = [k for k in need if k not in meta]
        return [f"{rid}: {META} lacks {missing} (the record drops out of every split and protocol)"] if missing else []
