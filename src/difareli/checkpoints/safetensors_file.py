"""A ``.safetensors`` file checked before its tensors are read: the 8-byte header length, the JSON header, and each
tensor's dtype, shape and byte range (together they must tile the data exactly). The format: an unsigned
little-endian 64-bit header length, a UTF-8 JSON object ``{name: {"dtype", "shape", "data_offsets": [begin, end]},
"__metadata__": {str: str}}``, then the raw data, offsets relative to its start.

Every problem is one line naming the file, the tensor and the fix (``fix``, given by the caller), never a
traceback from the reader; a PyTorch pickle or zip (a ``.ckpt`` renamed ``.safetensors``) is named as such.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from difareli.errors import UserError

#: Bytes per element of the dtypes difareli writes (floats for weights, integers and bools for buffers).
DTYPE_BYTES = {"F64": 8, "F32": 4, "F16": 2, "BF16": 2, "I64": 8, "I32": 4, "I16": 2, "I8": 1, "U8": 1, "BOOL": 1}
FLOAT_DTYPES = ("F64", "F32", "F16", "BF16")
#: The reader's own bound on a header (safetensors refuses larger ones).
MAX_HEADER = 100_000_000


def _kind_of(first: bytes) -> str | None:
    """What a file that is not safetensors is, from its first bytes (PyTorch writes zips, older ones pickles)."""
    if first.startswith(b"PK\x03\x04"):
        return "a zip archive (a PyTorch .ckpt saved by torch.save, renamed?)"
    if first[:1] == b"\x80" and first[1:2] in (b"\x02", b"\x03", b"\x04", b"\x05"):
        return "a Python pickle (an old PyTorch .ckpt, renamed?)"
    return None


def read_header(path: str | Path, fix: str) -> dict[str, dict[str, Any]]:
    """The tensors a safetensors file holds, ``{name: {"dtype", "shape", "data_offsets"}}``, after checking the
    header against the file (see the module doc); a problem is a UserError ``<path>: <what>; <fix>``."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        first = f.read(8)
        kind = _kind_of(first)
        if kind is not None:
            raise UserError(f"{path} is {kind}, not a safetensors file; give the .ckpt itself as checkpoint=<file>."
                            "ckpt, or make a folder from it: difareli-export <file>.ckpt <folder>")
        if len(first) < 8:
            raise UserError(f"{path}: {size} bytes, too short for a safetensors file (the 8-byte header length is "
                            f"cut): truncated; {fix}")
        n = int.from_bytes(first, "little")
        if n > min(size - 8, MAX_HEADER):
            raise UserError(f"{path}: its header claims {n} bytes, the file holds {size - 8} after the length: "
                            f"truncated or not a safetensors file; {fix}")
        raw = f.read(n)
    try:
        header = json.loads(raw.decode("utf-8"))
    except RecursionError:  # a few hundred nested brackets: no tensor list nests, so it was made to break readers
        raise UserError(f"{path}: its header nests arrays or objects too deeply to be a tensor list: corrupt; "
                        f"{fix}") from None
    except (UnicodeDecodeError, ValueError) as e:
        raise UserError(f"{path}: its header is not JSON ({str(e)[:80]}): corrupt; {fix}") from None
    if not isinstance(header, dict):
        raise UserError(f"{path}: its header is a JSON {type(header).__name__}, not an object: corrupt; {fix}")
    meta = header.pop("__metadata__", {})
    if not isinstance(meta, dict) or not all(isinstance(v, str) for v in meta.values()):
        raise UserError(f"{path}: its __metadata__ is not an object of strings: corrupt; {fix}")
    for name, entry in header.items():
        _check_entry(path, name, entry, fix)
    _check_tiling(path, header, size - 8 - n, fix)
    return header


def _check_entry(path: Path, name: str, entry: Any, fix: str) -> None:
    """One tensor's entry: a known dtype, a shape of non-negative integers, offsets spanning exactly its bytes."""
    where = f"{path}: tensor {name!r}"
    if not isinstance(entry, dict) or set(entry) != {"dtype", "shape", "data_offsets"}:
        raise UserError(f"{where}: its entry is not {{dtype, shape, data_offsets}}: corrupt; {fix}")
    dtype, shape, offsets = entry["dtype"], entry["shape"], entry["data_offsets"]
    if dtype not in DTYPE_BYTES:
        raise UserError(f"{where}: dtype {str(dtype)[:20]!r} is not one difareli weights use "
                        f"({', '.join(DTYPE_BYTES)}); {fix}")

    def ints(v: Any) -> bool:
        return isinstance(v, list) and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in v)

    if not ints(shape):
        raise UserError(f"{where}: shape {str(shape)[:40]} is not a list of non-negative integers: corrupt; {fix}")
    if not ints(offsets) or len(offsets) != 2 or offsets[0] > offsets[1]:
        raise UserError(f"{where}: data_offsets {str(offsets)[:40]} are not [begin, end] with begin <= end: "
                        f"corrupt; {fix}")
    need = math.prod(shape) * DTYPE_BYTES[dtype]
    if offsets[1] - offsets[0] != need:
        raise UserError(f"{where}: shape {tuple(shape)} of {dtype} needs {need} bytes, its data_offsets span "
                        f"{offsets[1] - offsets[0]}: the header lies; {fix}")


def _check_tiling(path: Path, header: dict, data: int, fix: str) -> None:
    """The tensors' byte ranges follow one another from 0 with no gap or overlap and end where the file does."""
    end, last = 0, None
    for name, entry in sorted(header.items(), key=lambda kv: tuple(kv[1]["data_offsets"])):
        begin = entry["data_offsets"][0]
        if begin != end:
            before = f"tensor {last!r} ends" if last else "the data starts"
            raise UserError(f"{path}: tensor {name!r} starts at byte {begin}, {before} at {end}: "
                            f"{'an overlap' if begin < end else 'a gap'}, the header lies; {fix}")
        end, last = entry["data_offsets"][1], name
    if end > data:
        raise UserError(f"{path}: tensor {last!r} ends at byte {end} of the data, the file holds {data}: "
                        f"truncated; {fix}")
    if end < data:
        raise UserError(f"{path}: {data - end} bytes after the last tensor {last!r}: not the file that was "
                        f"written; {fix}")
