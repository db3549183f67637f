"""Writing files so that nothing already written is lost or left half-written, and one writer per output folder.

- :func:`atomic_path` yields a temporary path *beside* the target (same folder, so same filesystem) and renames
  it into place only when the body finished; a kill at any moment leaves the previous file or the new one,
  never a torn one (``durable`` also fsyncs the file and its folder, against power loss).
- :func:`torch_save_atomic`, :func:`write_text_atomic`, :func:`write_json_atomic` are that for torch objects,
  text and JSON; a full disk is a :class:`~difareli.errors.UserError` naming the file, and the temporary file is
  removed.
- :func:`append_text` appends whole lines or nothing (a full disk truncates back what it began: resumable row
  logs), :func:`append_csv_row` a CSV row so (the header first), :func:`read_csv_rows` reads such a log back;
  :func:`on_full_disk` turns a full disk anywhere in a command's writes into the same one-line error and
  removes this process's scratch files (``*.tmp-<pid>``) that writers outside this module leave behind.
- :func:`folder_lock` holds an exclusive ``fcntl`` lock on ``<folder>/.difareli.lock`` for a command's whole run:
  a second concurrent writer into the same output folder stops at once with a message naming the first one's
  command and pid (the lock dies with its process, so a killed run never leaves a stale lock).
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import os
import shutil
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

from difareli.errors import UserError, is_no_space, os_reason

LOCK_NAME = ".difareli.lock"


def fsync_dir(folder: str | Path) -> None:
    """Make a rename in ``folder`` durable; best effort where the platform or file system cannot."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


NO_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
#: The fix of a full disk in a resumable command (records, rows or files already complete are kept).
RESUME = "free space and rerun the same command to resume (what was already written is complete and kept)"


class NoSpaceError(UserError):
    """A full disk (or quota) while writing ``path``: the message names the file and the fix."""

    def __init__(self, path: str | Path, err: OSError, fix: str | None = None):
        self.path, self.err = path, err
        fix = fix or "free space or write elsewhere (nothing already written was changed)"
        super().__init__(f"no space left on the device writing {path} ({os_reason(err)}); {fix}")


def no_space(path: str | Path, err: OSError, fix: str | None = None) -> UserError:
    """The one-line error for a full disk (or quota) while writing ``path``."""
    return NoSpaceError(path, err, fix)


def remove_scratch(folders: Iterable[str | Path]) -> None:
    """Remove this process's scratch files ``<folder>/*.tmp-<pid>`` (and ``.*.tmp-<pid>``): what a writer that
    renames into place leaves when a full disk stops it before the rename."""
    suffix = f".tmp-{os.getpid()}"
    for folder in folders:
        folder = Path(folder)
        if folder.is_dir():
            for p in folder.iterdir():
                if p.name.endswith(suffix) and p.is_file():
                    p.unlink(missing_ok=True)


@contextlib.contextmanager
def on_full_disk(what: str | Path, *, scratch: Iterable[str | Path] = (), fix: str | None = None) -> Iterator[None]:
    """Inside the body, a full disk becomes :func:`no_space` naming the file (the OSError's, else ``what``), after
    removing this process's scratch files in ``scratch`` folders; other errors pass unchanged."""
    try:
        yield
    except NoSpaceError as e:  # an atomic writer inside already named its file: give this command's fix
        remove_scratch(scratch)
        raise no_space(e.path, e.err, fix) from None
    except OSError as e:
        if not is_no_space(e):
            raise
        remove_scratch(scratch)
        raise no_space(e.filename or what, e, fix) from None


def append_text(path: str | Path, text: str, *, durable: bool = False, fix: str | None = None) -> Path:
    """Append ``text`` (whole lines) to ``path``, creating it: all of it or, on a full disk, none of it (the
    file is truncated back to its previous size and the error is :func:`no_space`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = text.encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        start = os.fstat(fd).st_size
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            if durable:
                os.fsync(fd)
        except OSError as e:
            if not is_no_space(e):
                raise
            os.ftruncate(fd, start)  # the lines already there stay whole; none is left half-written
            raise no_space(path, e, fix or RESUME) from None
    finally:
        os.close(fd)
    return path


def append_csv_row(path: str | Path, fields: Sequence[str], row: Mapping[str, Any], *,
                   fix: str | None = None) -> Path:
    """One CSV row (keys outside ``fields`` ignored; the header first into a new or empty file) appended whole or
    not at all (:func:`append_text`): a kill or a full disk loses at most the row in progress."""
    path, buf = Path(path), io.StringIO()
    w = csv.DictWriter(buf, list(fields), extrasaction="ignore")
    if not path.is_file() or path.stat().st_size == 0:
        w.writeheader()
    w.writerow(row)
    return append_text(path, buf.getvalue(), fix=fix)


def read_csv_rows(path: str | Path, key: str) -> dict[str, dict[str, str]]:
    """The rows of a CSV log (:func:`append_csv_row`) by their ``key`` column (a later row wins); {} for no file."""
    path = Path(path)
    if not path.is_file():
        return {}
    with path.open(newline="") as f:
        return {row[key]: row for row in csv.DictReader(f)}


@contextlib.contextmanager
def atomic_path(path: str | Path, *, durable: bool = False) -> Iterator[Path]:
    """Yield a temporary file path beside ``path``; rename it onto ``path`` when the ``with`` body succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        if durable:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        os.replace(tmp, path)
        if durable:
            fsync_dir(path.parent)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if is_no_space(e):
            raise no_space(path, e) from None
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def torch_save_atomic(obj: Any, path: str | Path, *, durable: bool = True) -> Path:
    """``torch.save`` into ``path`` atomically (checkpoints: durable by default)."""
    import torch

    with atomic_path(path, durable=durable) as tmp:
        with open(tmp, "wb") as f:
            torch.save(obj, f)
    return Path(path)


def save_npy_atomic(path: str | Path, array: Any, *, durable: bool = False) -> Path:
    """``np.save`` into ``path`` atomically (no pickles)."""
    import numpy as np

    with atomic_path(path, durable=durable) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array, allow_pickle=False)
    return Path(path)


def write_text_atomic(path: str | Path, text: str, *, durable: bool = False) -> Path:
    """Write ``text`` into ``path`` atomically."""
    with atomic_path(path, durable=durable) as tmp:
        tmp.write_text(text)
    return Path(path)


def read_json_mapping(path: str | Path) -> dict:
    """The JSON object in ``path``, or {} where the file is missing, unreadable or holds no object (callers that
    must refuse an unreadable record read it themselves)."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError, RecursionError):  # RecursionError: brackets nested thousands deep
        return {}
    return doc if isinstance(doc, dict) else {}


def write_json_atomic(path: str | Path, obj: Any, *, durable: bool = False, indent: int | None = 2) -> Path:
    """Write ``obj`` as JSON into ``path`` atomically (numpy values as lists, other objects as strings)."""
    text = json.dumps(obj, indent=indent, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    return write_text_atomic(path, text + "\n", durable=durable)


@contextlib.contextmanager
def folder_lock(folder: str | Path, command: str) -> Iterator[Path]:
    """Hold the exclusive lock of an output ``folder`` (created) for ``command``; a second holder is refused."""
    import fcntl

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / LOCK_NAME
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another difareli command"
            raise UserError(f"{folder} is being written by {holder}; wait for it to finish or give another output "
                            "folder") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"difareli-{command} (pid {os.getpid()})".encode(), 0)
        yield folder
    finally:
        os.close(fd)  # closing releases the lock


@contextlib.contextmanager
def staged_outputs(out_dir: str | Path, names: Iterable[str], last: str | None = None) -> Iterator[Path]:
    """Write a command's outputs into a scratch folder inside ``out_dir`` and publish them only when the block
    succeeds: the previous run's files of ``names`` are removed, then the new ones renamed into place (``last``,
    e.g. the summary, last of all), so the folder never mixes two runs; a block that fails (a full disk, a kill)
    leaves the previous outputs as they were and removes the scratch folder. Renames and removals need no space.
    A full disk in the block is one :class:`NoSpaceError` naming the output (not its scratch copy)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stage = out / f".partial-{os.getpid()}"
    stage.mkdir(exist_ok=True)
    try:
        yield stage
    except BaseException as e:
        shutil.rmtree(stage, ignore_errors=True)
        if isinstance(e, NoSpaceError):
            where, err = Path(e.path), e.err
        elif isinstance(e, OSError) and is_no_space(e):
            where, err = Path(e.filename or out), e
        else:
            raise
        where = out / where.name if where.parent == stage else where
        raise NoSpaceError(where, err, "free space or write elsewhere (the previous outputs are kept as they "
                                       "were)") from None
    made = sorted(p.name for p in stage.iterdir())
    for name in set(names) | set(made):
        if (out / name).is_file():
            (out / name).unlink()
    for name in sorted(made, key=lambda n: n == last):
        os.replace(stage / name, out / name)
    stage.rmdir()
    fsync_dir(out)
