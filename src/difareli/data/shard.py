"""Sharding per-record jobs: ``shard="i/n"`` picks the records of shard ``i`` of ``n``, deterministically.

Every per-record job (``difareli-preprocess``, ``difareli-synth``, ``difareli-benchmark``, and the teacher-pair
and shadow-map generators once they exist) takes the same option and does::

    from difareli.data import shard
    spec = shard.parse(cfg.shard)                      # None, or Shard(index=i, count=n)
    todo = shard.select(all_items, spec, key=record_id)

Membership is a **stable hash of the record id** (BLAKE2b, not Python's salted ``hash``), not a block of a
sorted list: a record's shard depends on its id alone, so shards started at different times (SLURM array tasks,
a folder that gained photos meanwhile, a resumed run) can never disagree about who owns a record. The union of
the n shards is exactly the unsharded set and no record is done twice. Sizes are balanced in expectation
(n records per shard ± sqrt), which is what matters at FFHQ scale.

Shards write into one store concurrently: :meth:`EncodingStore.write` renames each record into place whole and
``clean_scratch`` only removes scratch folders of dead processes. Benchmark shards write one run dir each, with
a :data:`MARKER` file; :func:`check_complete` (used by ``difareli-table``) refuses a merge with a shard missing.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence, TypeVar

from difareli.errors import UserError
from difareli.utils.fileio import write_text_atomic

T = TypeVar("T")

#: Written by a sharded benchmark run into its run dir: ``{"shard": "i/n", "job": {...}}``.
MARKER = "shard.json"

_SPEC = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")


@dataclass(frozen=True)
class Shard:
    """Shard ``index`` (0-based) of ``count``."""

    index: int
    count: int

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"

    def owns(self, key: str) -> bool:
        """Whether the record with id ``key`` belongs to this shard."""
        return shard_of(key, self.count) == self.index

    @property
    def suffix(self) -> str:
        """A file-name tag for per-shard outputs, e.g. ``shard-0-of-4``."""
        return f"shard-{self.index}-of-{self.count}"


def parse(spec: Any) -> Shard | None:
    """``None``/``""`` -> None (no sharding); ``"i/n"`` with ``0 <= i < n`` -> :class:`Shard`.

    Raises ValueError naming the value and the expected form.
    """
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        return None
    if isinstance(spec, Shard):
        return spec
    m = _SPEC.match(str(spec))
    if not m:
        raise UserError(f"shard={spec!r} is invalid: use 'i/n' with 0 <= i < n, e.g. shard=0/4 (quote it in a "
                        "multirun: 'shard=0/2,1/2')")
    i, n = int(m.group(1)), int(m.group(2))
    if n < 1 or not 0 <= i < n:
        raise UserError(f"shard={spec!r} is invalid: the index must satisfy 0 <= i < n (got i={i}, n={n})")
    return Shard(i, n)


def shard_of(key: str, count: int) -> int:
    """The shard (0..count-1) owning ``key``: BLAKE2b-64 of the UTF-8 id modulo ``count`` (stable across
    processes, machines and Python versions)."""
    digest = hashlib.blake2b(str(key).encode("utf-8"), digest_size=8).digest()
    return int.from_bytes(digest, "big") % count


def select(items: Iterable[T], shard: Shard | str | None, key: Callable[[T], str] = str) -> list[T]:
    """The items of ``shard`` (all of them when ``shard`` is None), in their original order."""
    spec = parse(shard)
    items = list(items)
    if spec is None or spec.count == 1:
        return items
    return [it for it in items if spec.owns(key(it))]


# ------------------------------------------------------------------------------ sharded run dirs (benchmarks)
def write_marker(run_dir: str | Path, shard: Shard, job: Mapping[str, Any]) -> Path:
    """Record in ``run_dir`` that it holds shard ``shard`` of ``job`` (a JSON-able description of what was
    sharded: everything but the shard itself)."""
    path = Path(run_dir) / MARKER
    path.parent.mkdir(parents=True, exist_ok=True)
    # Atomic: a full disk or a kill leaves no truncated marker (difareli-table would refuse the shard).
    write_text_atomic(path, json.dumps({"shard": str(shard), "job": dict(job)}, sort_keys=True, indent=1) + "\n")
    return path


def check_complete(run_dirs: Sequence[str | Path]) -> dict[str, list[Path]]:
    """Group sharded run dirs by job and check every job has each of its shards exactly once.

    Run dirs without a :data:`MARKER` are ignored (unsharded runs). Returns ``{job json: [dirs]}``; raises
    a UserError naming the job's run dirs and the missing or repeated shards.
    """
    groups: dict[str, dict[int, list[Path]]] = {}
    counts: dict[str, int] = {}
    for d in run_dirs:
        path = Path(d) / MARKER
        if not path.is_file():
            continue
        try:
            doc = json.loads(path.read_text())
            spec, job = parse(doc["shard"]), json.dumps(doc["job"], sort_keys=True)
        except (ValueError, KeyError, TypeError):
            raise UserError(f"{path}: not a shard marker (JSON with 'shard' and 'job'); rerun that shard's benchmark "
                            "or leave its run dir out") from None
        if counts.setdefault(job, spec.count) != spec.count:
            raise UserError(f"{path}: shard {spec} but other shards of the same job are out of {counts[job]}")
        groups.setdefault(job, {}).setdefault(spec.index, []).append(Path(d))
    for job, by_index in groups.items():
        n = counts[job]
        missing = [f"{i}/{n}" for i in range(n) if i not in by_index]
        repeated = [f"{i}/{n} ({', '.join(map(str, ps))})" for i, ps in by_index.items() if len(ps) > 1]
        if missing or repeated:
            # The job is named by what a user recognises (its run dirs, method and store), not its whole settings.
            dirs = ", ".join(str(p) for ps in by_index.values() for p in ps[:1])
            raise UserError(f"run dir(s) {dirs} hold shards of one benchmark job ({_job_name(job)}): "
                            + (f"shard(s) {', '.join(missing)} missing" if missing else "")
                            + ("; " if missing and repeated else "")
                            + (f"shard(s) listed twice: {'; '.join(repeated)}" if repeated else "")
                            + "; list every shard's run dir exactly once (rerun a missing one with shard=i/n)")
    return {job: [p for i in sorted(ix) for p in ix[i]] for job, ix in groups.items()}


def _job_name(job: str) -> str:
    """A sharded job in a few words: its method and store (from the marker's job description)."""
    doc = json.loads(job)
    method = doc.get("method")
    name = (method.get("name") or str(method.get("_target_") or "").rpartition(".")[2]
            if isinstance(method, Mapping) else method)
    store = doc.get("store")
    return ", ".join(x for x in (f"method {name}" if name else "", f"store {store}" if store else "") if x) or "?"
