"""What produced a resumable output, so a rerun never mixes results of different inputs.

Resumable outputs (benchmark rows, teacher pairs, ablation rows) record the provenance that produced them: the
checkpoint's identity by content hash (not its path: ``last.ckpt`` is rewritten in place), the store's identity
(its header and record count), the sampler and the settings. A rerun into the same folder compares its own
provenance with the recorded one and is refused, naming what differs, instead of reusing stale results.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Mapping

from difareli.checkpoints import loading
from difareli.errors import UserError
from difareli.utils.fileio import write_json_atomic

PROVENANCE = "provenance.json"
_DIGESTS: dict[tuple[str, int, int], str] = {}


def file_digest(path: str | Path, chars: int = 16) -> str:
    """SHA-256 of a file's bytes (first ``chars`` hex digits), cached by path, size and mtime."""
    p = Path(path).resolve()
    st = p.stat()
    key = (str(p), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _DIGESTS[key] = h.hexdigest()
    return _DIGESTS[key][:chars]


def checkpoint_identity(checkpoint: Any) -> str:
    """``sha256:<digest>`` of a checkpoint given as a path or a shipped name
    (:func:`difareli.checkpoints.loading.resolve`)."""
    return f"sha256:{file_digest(loading.resolve(str(checkpoint)))}"


def store_identity(store) -> str:
    """A store's identity: its header's generator settings, dims and encodings (derived versions added later,
    such as difference shadow maps, do not change it; a version read in place of its base is a setting)."""
    header = {"dims": store.dims, "encodings": list(store.encodings), "meta": store.store_meta}
    return "sha256:" + hashlib.sha256(json.dumps(header, sort_keys=True, default=str).encode()).hexdigest()[:16]


def model_identity(model) -> str:
    """``weights:<digest>`` of a module's state dict (names, shapes, dtypes and values): the same weights give
    the same identity whichever file (run checkpoint, slim export) they came from."""
    import torch

    h = hashlib.sha256()
    for name, value in sorted(model.state_dict().items()):
        h.update(f"{name}:{tuple(value.shape)}:{value.dtype}".encode())
        t = value.detach().cpu().contiguous()
        h.update((t.view(torch.uint8) if t.dtype != torch.bool else t.to(torch.uint8)).numpy().tobytes())
    return f"weights:{h.hexdigest()[:16]}"


def plain(obj: Any) -> Any:
    """``obj`` as JSON-comparable plain data (OmegaConf containers, tuples and paths included)."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(obj, (DictConfig, ListConfig)):
            obj = OmegaConf.to_container(obj, resolve=True)
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    return json.loads(json.dumps(obj, sort_keys=True, default=str))


def differences(have: Mapping[str, Any], want: Mapping[str, Any]) -> dict[str, tuple[Any, Any]]:
    """``{key: (recorded, this run)}`` for every key whose values differ."""
    return {k: (have.get(k), want.get(k)) for k in sorted(set(have) | set(want)) if have.get(k) != want.get(k)}


def ensure(folder: str | Path, want: Mapping[str, Any], what: str, *, has_results: bool | None = None,
           name: str = PROVENANCE) -> None:
    """Record ``want`` in ``folder``/``name`` (default provenance.json), or check it against the recorded one.

    A folder that already holds results (``has_results``, default: any file but the provenance) without a record
    of what made them is refused too: nothing says they match. A record of other settings over no results (a run
    that stopped before its first one, e.g. on a store without pairs) is replaced: nothing was made under it.
    """
    folder = Path(folder)
    path = folder / name
    want = plain(dict(want))
    if has_results is None:
        has_results = folder.is_dir() and any(p.name not in (name, ".difareli.lock") for p in folder.iterdir())
    if path.is_file():
        try:
            have = json.loads(path.read_text())
        except (OSError, ValueError, RecursionError) as e:
            raise UserError(f"{path} is unreadable ({str(e)[:120]}); remove {folder} to redo {what}") from None
        diff = differences(have, want)
        if not diff:
            return
        if has_results:
            lines = "; ".join(f"{k}: {a!r} there, {b!r} now" for k, a, b in ((k, *v) for k, v in diff.items()))
            raise UserError(f"{folder} holds {what} made with other settings ({lines}); give another output folder "
                            f"or remove {folder}")
    if has_results:
        raise UserError(f"{folder} holds {what} without a record of what made them ({name}); give another "
                        f"output folder or remove {folder}")
    write_json_atomic(path, want)
