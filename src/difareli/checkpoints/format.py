"""The checkpoint format: the keys difareli writes beside Lightning's, which keys a slim (shipped) checkpoint
keeps, the translation of older formats, and the two files a checkpoint is stored as: a ``.ckpt`` (any torch file,
read with ``torch.load(weights_only=True)``: :func:`load_torch_file`) and a weights folder (``model.safetensors`` +
``config.json`` + ``README.md``, written by :mod:`difareli.checkpoints.export`; read with no pickle at all:
:func:`read_folder`, the safetensors header checked against the file first, :func:`read_header`). Every problem
is one line naming the file (and the key or tensor) and the fix. Used by the Lightning modules,
:mod:`difareli.checkpoints.loading`, :mod:`difareli.checkpoints.zoo` and the authors' weights' import; nothing
here imports any of them, and torch loads only when a file is read.

Checkpoints written before format 2 (flat ``spatial_type`` / ``modulate_skips`` / ``lr`` / ``weight_decay``,
statistics in ``state_dict`` buffers) are translated by :func:`upgrade_checkpoint`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from difareli.errors import UserError, UserFileNotFoundError

if TYPE_CHECKING:
    import torch

#: The module class that wrote a checkpoint (``package.module.Class``) and the format version.
MODULE_KEY, FORMAT_KEY, FORMAT_VERSION = "difareli_module", "difareli_format", 2
#: The class of checkpoints that predate ``difareli_module`` (all of them were DiffusionModules).
LEGACY_MODULE = "difareli.lit.diffusion.DiffusionModule"
#: Keys a slim checkpoint keeps from a Lightning checkpoint.
SLIM_KEYS = ("state_dict", "hyper_parameters", "global_step", "epoch", MODULE_KEY, FORMAT_KEY,
             "pytorch-lightning_version")


def stamp(checkpoint: dict[str, Any], module: object) -> None:
    """Record ``module``'s class and the current format in a checkpoint dict being saved."""
    checkpoint[MODULE_KEY] = f"{type(module).__module__}.{type(module).__qualname__}"
    checkpoint[FORMAT_KEY] = FORMAT_VERSION


def upgrade_checkpoint(ckpt: dict[str, Any], where: Any = None) -> dict[str, Any]:
    """Translate a pre-format-2 checkpoint dict in place (and return it); current ones pass unchanged, and one of a
    format newer than this code reads (or not an integer) is a UserError naming ``where`` (its file or folder).

    ``spatial_type`` + ``modulate_skips`` -> ``spatial: {type, modulate_skips}``; ``lr`` + ``weight_decay`` ->
    ``optimizer`` (AdamW, as trained); ``ns_mean`` / ``ns_std`` buffers -> ``nonspatial_stats`` lists;
    ``adagn_out_silu`` -> ``False`` (those networks had no output SiLU).
    """
    version = ckpt.get(FORMAT_KEY, 1)
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= FORMAT_VERSION:
        # read as the current format, a newer one's keys would be built into a model that means something else
        raise UserError(f"{f'checkpoint={where}' if where else 'the checkpoint'}: {FORMAT_KEY} is "
                        f"{repr(version)[:40]}, not a format this difareli "
                        f"reads (1 to {FORMAT_VERSION}); load it with the difareli version that wrote it")
    if version == FORMAT_VERSION:
        return ckpt
    hp = dict(ckpt["hyper_parameters"])
    kind, skips = hp.pop("spatial_type", "modulator"), hp.pop("modulate_skips", False)
    if kind in (None, "none") or not hp.get("spatial_inputs"):
        hp["spatial"] = None
    else:  # modulate_skips was the Modulator's option; no other component took one
        hp["spatial"] = {"type": kind, **({"modulate_skips": bool(skips)} if kind == "modulator" else {})}
    hp["optimizer"] = {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": float(hp.pop("lr", 1e-4)),
                       "weight_decay": float(hp.pop("weight_decay", 0.0))}
    hp.setdefault("scheduler", None)
    hp.setdefault("adagn_out_silu", bool(dict(hp.get("net_overrides") or {}).get("adagn_out_silu", False)))
    stats = None
    for key in ("state_dict", "current_model_state"):  # the EMA callback keeps the raw weights in the latter
        if key in ckpt:
            sd = dict(ckpt[key])
            mean, std = sd.pop("ns_mean", None), sd.pop("ns_std", None)
            ckpt[key] = sd
            if key == "state_dict" and mean is not None:
                stats = {"mean": mean.float().tolist(), "std": std.float().tolist()}
    hp["nonspatial_stats"] = stats
    ckpt["hyper_parameters"] = hp
    ckpt.setdefault(MODULE_KEY, LEGACY_MODULE)
    ckpt[FORMAT_KEY] = FORMAT_VERSION
    return ckpt


# ---------------------------------------------------------------------------------------------- official files
#: The official DiFaReli code, whose checkpoints difareli-import-checkpoint converts (difareli.official.weights).
OFFICIAL_REPO = "github.com/diffusion-face-relighting/difareli_code"


def is_official(obj: Any) -> str | None:
    """``"unet"`` / ``"modulator"`` if ``obj`` is an official state dict (UNet / Modulator), else None."""
    if not isinstance(obj, Mapping) or "hyper_parameters" in obj or "input_blocks.0.0.weight" not in obj:
        return None
    return "unet" if "time_embed.0.weight" in obj else "modulator"


def refuse_official(obj: Any, path: Any) -> None:
    """Raise the one-line message that names the import command when ``obj`` (loaded from ``path``) is an
    official state dict; a no-op otherwise. Every loader (``lit.read_checkpoint``) calls it."""
    role = is_official(obj)
    if role is not None:
        raise UserError(f"checkpoint={path} is an official DiFaReli {role} state dict ({OFFICIAL_REPO}); convert it "
                        f"once: difareli-import-checkpoint {path} config=<its official YAML> out=<name>.ckpt, then "
                        "use checkpoint=<name>.ckpt")


def training_resolution(config: Mapping[str, Any] | None) -> int | None:
    """The image size (px) a checkpoint was trained at, from its hyperparameters (``input_dims.resolution``, which
    difareli-train takes from the DataModule), or None where it records none."""
    dims = dict((config or {}).get("input_dims") or {})
    res = dims.get("resolution")
    return int(res) if res else None


# ---------------------------------------------------------------------------------------------- files
WEIGHTS, CONFIG, CARD = "model.safetensors", "config.json", "README.md"
#: ``config.json``'s ``format``: what wrote the folder, so another folder with a config.json is never mistaken.
FOLDER_FORMAT = "difareli-weights-folder"
FOLDER_VERSION = 1
#: Checkpoint keys config.json carries (besides the state dict, which goes to model.safetensors).
CONFIG_KEYS = ("hyper_parameters", "global_step", "epoch", MODULE_KEY, FORMAT_KEY, "pytorch-lightning_version",
               "model_card")


def is_folder(path: str | Path) -> bool:
    """Whether ``path`` is a weights folder (a directory holding :data:`WEIGHTS` and :data:`CONFIG`)."""
    p = Path(path)
    return p.is_dir() and (p / WEIGHTS).is_file() and (p / CONFIG).is_file()


def _entry_kind(path: Path) -> str | None:
    """What ``path`` is where a weights folder needs a regular file: None for a file, else its kind in words."""
    import stat

    try:
        mode = path.stat().st_mode
    except OSError:
        return "a symbolic link that leads nowhere" if path.is_symlink() else None
    return (None if stat.S_ISREG(mode) else "a folder" if stat.S_ISDIR(mode) else
            "a FIFO (named pipe)" if stat.S_ISFIFO(mode) else
            "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")


def folder_problem(path: str | Path) -> str | None:
    """Why ``path``, a folder holding one of a weights folder's two files, is not one (None for anything else):
    the other file missing, or either one there but not a regular file (a folder, a FIFO, a device, a dead link)."""
    p = Path(path)
    if not p.is_dir():
        return None
    have = [n for n in (WEIGHTS, CONFIG) if (p / n).is_file()]
    odd = [(n, _entry_kind(p / n)) for n in (WEIGHTS, CONFIG)
           if n not in have and ((p / n).is_symlink() or (p / n).exists())]
    fix = "copy the folder again whole, or export it again: difareli-export <checkpoint>.ckpt <folder>"
    if have and odd:
        return f"checkpoint={p}: its {odd[0][0]} is {odd[0][1]}, not the file a weights folder holds; {fix}"
    if len(have) != 1:
        return None
    lacks = CONFIG if have == [WEIGHTS] else WEIGHTS
    return f"checkpoint={p} is a weights folder without {lacks} (it holds {have[0]}); {fix}"


def read_folder(folder: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The checkpoint dict of a weights folder (``state_dict`` from safetensors, the rest from JSON); no pickle.
    ``config.json`` is checked against its schema (:func:`check_config`) and the safetensors header against the
    file (:func:`read_header`) before any tensor is read."""
    import torch
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    folder = Path(folder)
    fix = f"export the folder again: difareli-export <checkpoint>.ckpt {folder}"
    try:
        if (folder / CONFIG).stat().st_size > MAX_CONFIG_BYTES:
            raise UserError(f"{folder / CONFIG}: over {MAX_CONFIG_BYTES >> 20} MiB, not a weights folder's config; "
                            f"{fix}")
        config = json.loads((folder / CONFIG).read_text(encoding="utf-8"))
    except RecursionError:  # thousands of nested brackets: no config nests so, made to break the reader
        raise UserError(f"{folder / CONFIG}: nests arrays or objects too deeply to be a weights folder's config; "
                        f"{fix}") from None
    except (OSError, ValueError) as e:
        if isinstance(e, UserError):
            raise
        raise UserError(f"{folder / CONFIG}: unreadable ({str(e)[:120]}); {fix}") from None
    check_config(config, folder / CONFIG, fix)
    read_header(folder / WEIGHTS, fix)
    device = str(torch.device(map_location)) if not isinstance(map_location, str) else map_location
    ckpt = {k: config[k] for k in CONFIG_KEYS if k in config}
    try:
        ckpt["state_dict"] = load_file(folder / WEIGHTS, device=device)
    except (SafetensorError, OSError, ValueError) as e:  # changed under us since the header was checked
        raise UserError(f"{folder / WEIGHTS}: unreadable ({str(e)[:120]}); {fix}") from None
    return ckpt


# ---------------------------------------------------------------------------------------------- model.safetensors
#: Bytes per element of the dtypes difareli writes (floats for weights, integers and bools for buffers).
DTYPE_BYTES = {"F64": 8, "F32": 4, "F16": 2, "BF16": 2, "I64": 8, "I32": 4, "I16": 2, "I8": 1, "U8": 1, "BOOL": 1}
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
    header against the file: a little-endian 64-bit header length, a UTF-8 JSON object ``{name: {"dtype",
    "shape", "data_offsets": [begin, end]}, "__metadata__": {str: str}}``, then the data, whose tensors' byte ranges
    must tile it exactly. A problem is a UserError ``<path>: <what>; <fix>``."""
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


# ---------------------------------------------------------------------------------------------- config.json schema
#: The largest training resolution a checkpoint may state (px). The paper's models are 256 px; a config.json that
#: states more is a typo or a lie, and a photo relight would allocate gigabytes at that size before anything failed.
MAX_RESOLUTION = 1024
MAX_CONFIG_BYTES = 64 * 2 ** 20
#: The largest step or epoch count a config may state (a signed 64-bit integer, what Lightning counts in).
MAX_COUNT = 2 ** 63 - 1
#: config.json's keys: key -> (required, JSON type). Any other key is refused.
CONFIG_SCHEMA = {"format": (True, str), "version": (True, int), MODULE_KEY: (True, str),
                 "hyper_parameters": (True, dict), FORMAT_KEY: (False, int), "global_step": (False, int),
                 "epoch": (False, int), "pytorch-lightning_version": (False, str), "model_card": (False, dict),
                 "source": (False, dict)}
#: ``hyper_parameters.input_dims``: key -> (lowest, highest).
INPUT_DIMS = {"resolution": (8, MAX_RESOLUTION), "spatial_channels": (0, 4096), "nonspatial_dim": (0, 1 << 20)}
_JSON = {dict: "an object", list: "an array", str: "a string", int: "an integer", float: "a number",
         bool: "true or false", type(None): "null"}


def json_is(value: Any, kind: type) -> bool:
    """JSON typing (a config's values and a checkpoint's hyperparameters): an integer is not a bool; a number may
    be an integer."""
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, kind)


def _wrong(where: Path, key: str, value: Any, want: str, fix: str) -> UserError:
    plain = isinstance(value, (str, int, float, bool, type(None)))
    text = json.dumps(value)
    shown = (text if len(text) <= 40 else f"{text[:30]}... ({len(text)} characters)") if plain else \
        _JSON.get(type(value), f"a {type(value).__name__}")
    return UserError(f"{where}: {key} is {shown}, must be {want}; {fix}")


def check_config(config: Any, where: Path, fix: str) -> None:
    """A weights folder's ``config.json`` against its schema: the format and version, the required keys and no
    unknown ones, each of its type, and bounds (steps >= 0, :data:`INPUT_DIMS`); one line naming the key."""
    if not isinstance(config, dict) or config.get("format") != FOLDER_FORMAT:
        raise UserError(f"{where} is not a difareli weights folder's config (no \"format\": \"{FOLDER_FORMAT}\"); "
                        "make one with difareli-export <checkpoint> <folder>")
    version = config.get("version")
    if json_is(version, int) and version > FOLDER_VERSION:
        raise UserError(f"{where.parent} is a weights folder of version {version}, newer than this difareli reads "
                        f"({FOLDER_VERSION}); load it with the difareli version that wrote it")
    fmt = config.get(FORMAT_KEY)
    if json_is(fmt, int) and fmt > FORMAT_VERSION:
        raise UserError(f"{where}: {FORMAT_KEY} is {fmt}, newer than this difareli reads ({FORMAT_VERSION}); load it "
                        "with the difareli version that wrote it")
    unknown = sorted(set(config) - set(CONFIG_SCHEMA))
    if unknown:
        raise UserError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(CONFIG_SCHEMA)}); {fix}")
    for key, (required, kind) in CONFIG_SCHEMA.items():
        if key not in config:
            if required:
                raise UserError(f"{where}: the required key {key!r} is missing; {fix}")
            continue
        if not json_is(config[key], kind):
            raise _wrong(where, key, config[key], _JSON[kind], fix)
    if not config[MODULE_KEY].startswith("difareli."):  # said here, naming the file: the loader would not import it
        raise _wrong(where, MODULE_KEY, config[MODULE_KEY], "a model class under difareli. (a checkpoint is data: "
                     "no other module is imported)", fix)
    for key, lo, hi in (("version", 1, FOLDER_VERSION), ("global_step", 0, MAX_COUNT), ("epoch", 0, MAX_COUNT),
                        (FORMAT_KEY, 1, FORMAT_VERSION)):
        if key in config and not lo <= config[key] <= hi:
            raise _wrong(where, key, config[key], f"an integer from {lo} to {hi}", fix)
    source = config.get("source", {})
    if set(source) - {"file", "sha256"} or not all(isinstance(v, str) for v in source.values()):
        raise _wrong(where, "source", source, "an object {file, sha256} of strings", fix)
    card = config.get("model_card", {})
    if not all(isinstance(v, (str, int, float, bool)) for v in card.values()):
        raise _wrong(where, "model_card", card, "an object of strings and numbers", fix)
    check_hyper_parameters(config["hyper_parameters"], where, fix)


def check_hyper_parameters(hp: Any, where: Any, fix: str) -> None:
    """The hyperparameters every module reads at load, typed and bounded: ``input_dims`` (:data:`INPUT_DIMS`),
    the input names and the normalisation statistics (finite, positive stds). The module checks the rest when it is
    built (:func:`build_module`)."""
    if not isinstance(hp, dict):
        raise _wrong(where, "hyper_parameters", hp, "an object", fix)
    dims = hp.get("input_dims")
    if not isinstance(dims, dict) or set(dims) != set(INPUT_DIMS):
        raise _wrong(where, "hyper_parameters.input_dims", dims, f"an object {{{', '.join(INPUT_DIMS)}}}", fix)
    for key, (lo, hi) in INPUT_DIMS.items():
        if not json_is(dims[key], int) or not lo <= dims[key] <= hi:
            raise _wrong(where, f"hyper_parameters.input_dims.{key}", dims[key], f"an integer from {lo} to {hi}"
                         + (" (px; the paper's models are 256)" if key == "resolution" else ""), fix)
    for key in ("spatial_inputs", "nonspatial_inputs"):
        value = hp.get(key, [])
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):  # a .ckpt's: tuples
            raise _wrong(where, f"hyper_parameters.{key}", value, "an array of encoding names", fix)
    stats = hp.get("nonspatial_stats")
    if stats is None:
        return
    ok = isinstance(stats, dict) and set(stats) == {"mean", "std"} and all(
        isinstance(stats[k], (list, tuple)) and len(stats[k]) == dims["nonspatial_dim"]
        and all(json_is(v, float) and math.isfinite(v) for v in stats[k]) for k in stats)
    if not ok or not all(v > 0 for v in stats["std"]):
        raise _wrong(where, "hyper_parameters.nonspatial_stats", stats, f"null or {{mean, std}}: "
                     f"{dims['nonspatial_dim']} finite numbers each (input_dims.nonspatial_dim), stds > 0", fix)


def load_torch_file(path: Any, what: str = "checkpoint", map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)``; a missing, truncated or non-torch file is a UserError naming
    it (never a hint to load untrusted pickles)."""
    import torch

    p = Path(str(path))
    if not p.is_file():
        raise UserFileNotFoundError(f"{what} {p} does not exist (difareli-train writes <run>/checkpoints/last.ckpt)")
    try:
        return torch.load(p, map_location=map_location, weights_only=True)
    except Exception as e:  # random bytes reach the unpickler's internals: KeyError, struct.error, ...
        size = p.stat().st_size
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if "weights_only" in first or "Weights only load failed" in first:
            first = "it holds objects other than tensors and plain containers"
        raise UserError(f"{what} {p} ({size} bytes) is not a readable PyTorch file ({first[:160]}); it may be "
                        "truncated or corrupt: copy it again or use another checkpoint") from None
