"""A store's record folders: their ids, their ``meta.json``, and how one is written so it appears whole or not at all.

A record is written into ``records/.tmp-<record_id>-<pid>/`` and renamed into place with one ``os.rename``; an
overwrite first renames the old folder to ``.old-<record_id>-<pid>``. A killed run therefore never leaves a partial
record, and :func:`clean_scratch` (run when a writer opens the store) removes the scratch folders of dead writers and
restores a record whose overwrite was cut between the two renames. :class:`~difareli.data.store.EncodingStore`
validates the arrays against its header and calls :func:`write_atomic`.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from difareli.errors import UserError
from difareli.utils.fileio import RESUME, fsync_dir, is_no_space, no_space

RECORDS = "records"
META = "meta.json"
_TMP = ".tmp-"
_OLD = ".old-"
_ID_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+=-]{0,199}$")


def validate_record_id(record_id: str) -> str:
    """Return ``record_id`` if it is a safe folder name, else raise a UserError saying why."""
    if not is_record_id(record_id):
        raise UserError(
            f"invalid record id {record_id!r}: use 1-200 characters from [A-Za-z0-9_.+=-], "
            "not starting with '.' or '-' (no '/', no spaces)"
        )
    return record_id


def is_record_id(record_id: object) -> bool:
    """Whether ``record_id`` is a string that may name a record folder (never a scratch folder)."""
    return isinstance(record_id, str) and _ID_RE.match(record_id) is not None


def _json_default(obj: Any) -> Any:
    # numpy scalars/arrays sneak into meta from generators; store them as plain JSON values.
    if isinstance(obj, (np.generic, np.ndarray)):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


def dump_meta(record_id: str, meta: Mapping[str, Any] | None) -> str:
    """The text of a record's ``meta.json`` (numpy values and paths as plain JSON); a UserError if not JSON."""
    try:
        return json.dumps(dict(meta or {}), indent=1, sort_keys=True, default=_json_default)
    except TypeError as e:
        raise UserError(f"record {record_id!r}: meta is not JSON-serialisable: {e}") from None


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


def clean_scratch(records_dir: Path) -> list[str]:
    """Remove the ``.tmp-*`` folders of dead writers and restore records whose overwrite was interrupted; returns
    the names of the scratch folders handled."""
    removed = []
    for entry in os.scandir(records_dir):
        parsed = _split_scratch(entry.name)
        if parsed is None or _pid_alive(parsed[2]):
            continue  # a live writer (another process on this host) still owns it
        kind, rid, _ = parsed
        final = records_dir / rid
        if kind == _OLD and not final.exists():
            # Killed between "rename old away" and "rename new in": the old record is still whole.
            os.rename(entry.path, final)
        else:
            shutil.rmtree(entry.path, ignore_errors=True)
        removed.append(entry.name)
    return removed


def write_atomic(records_dir: Path, record_id: str, arrays: Mapping[str, np.ndarray], meta_text: str, *,
                 overwrite: bool, durable: bool) -> bool:
    """Write the folder ``records_dir/record_id`` (one ``<name>.npy`` per array, ``meta.json``) in one rename;
    False (nothing written) if it exists and not ``overwrite``, or a concurrent writer of the id finished first.
    ``durable`` fsyncs each file and folder; a full disk is the one-line error naming the file."""
    final = records_dir / record_id
    tmp = records_dir / f"{_TMP}{record_id}-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    file = final
    try:
        tmp.mkdir()
        for name, arr in arrays.items():
            file = final / f"{name}.npy"
            with open(tmp / file.name, "wb") as f:
                np.save(f, arr, allow_pickle=False)
                _sync(f, durable)
        file = final / META
        with open(tmp / META, "w") as f:
            f.write(meta_text + "\n")
            _sync(f, durable)
        if durable:
            fsync_dir(tmp)
        return _commit(tmp, final, overwrite, durable)
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)  # a full disk or a kill leaves no partial record
        if is_no_space(e):
            raise no_space(file, e, RESUME) from None
        raise


def _sync(f, durable: bool) -> None:
    if durable:
        f.flush()
        os.fsync(f.fileno())


def _commit(tmp: Path, final: Path, overwrite: bool, durable: bool) -> bool:
    old = None
    if final.exists():
        if not overwrite:
            shutil.rmtree(tmp)  # another writer finished it meanwhile
            return False
        old = final.parent / f"{_OLD}{final.name}-{os.getpid()}"
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
    if durable:
        fsync_dir(final.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return True
