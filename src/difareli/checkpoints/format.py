"""The checkpoint format: the keys difareli writes beside Lightning's, which keys a slim (shipped) checkpoint
keeps, the translation of older formats, and the two files a checkpoint is stored as: a ``.ckpt`` (any torch file,
read with ``torch.load(weights_only=True)``: :func:`load_torch_file`) and a weights folder (``model.safetensors`` +
``config.json`` + ``README.md``, written by :mod:`difareli.checkpoints.export`; read with no pickle at all:
:func:`read_folder`). Used by the Lightning modules, :mod:`difareli.checkpoints.loading`,
:mod:`difareli.checkpoints.zoo` and the authors' weights' import; nothing here imports any of them.

Checkpoints written before format 2 (flat ``spatial_type`` / ``modulate_skips`` / ``lr`` / ``weight_decay``,
statistics in ``state_dict`` buffers) are translated by :func:`upgrade_checkpoint`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping

import torch

from difareli.errors import UserError, UserFileNotFoundError

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
    file (:func:`~difareli.checkpoints.safetensors_file.read_header`) before any tensor is read."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from difareli.checkpoints.safetensors_file import read_header

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


def _is(value: Any, kind: type) -> bool:
    """JSON typing: an integer is not a bool; a number may be an integer."""
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
    if _is(version, int) and version > FOLDER_VERSION:
        raise UserError(f"{where.parent} is a weights folder of version {version}, newer than this difareli reads "
                        f"({FOLDER_VERSION}); load it with the difareli version that wrote it")
    fmt = config.get(FORMAT_KEY)
    if _is(fmt, int) and fmt > FORMAT_VERSION:
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
        if not _is(config[key], kind):
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
        if not _is(dims[key], int) or not lo <= dims[key] <= hi:
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
        and all(_is(v, float) and math.isfinite(v) for v in stats[k]) for k in stats)
    if not ok or not all(v > 0 for v in stats["std"]):
        raise _wrong(where, "hyper_parameters.nonspatial_stats", stats, f"null or {{mean, std}}: "
                     f"{dims['nonspatial_dim']} finite numbers each (input_dims.nonspatial_dim), stds > 0", fix)


def load_torch_file(path: Any, what: str = "checkpoint", map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)``; a missing, truncated or non-torch file is a UserError naming
    it (never a hint to load untrusted pickles)."""
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


# ---------------------------------------------------------------------------------------------- the weights
def check_finite_state(state: Mapping[str, Any], where: Any, fix: str) -> None:
    """Every floating tensor of ``state`` is finite; the first that is not is a UserError naming it (the weights
    themselves are bad, whatever precision a run would use)."""
    for name, t in state.items():
        if isinstance(t, torch.Tensor) and t.is_floating_point() and t.numel():
            bad = int((~torch.isfinite(t)).sum())
            if bad:
                raise UserError(f"{where}: tensor {name!r} holds {bad} NaN/Inf value(s) of {t.numel()}: the weights "
                                f"are corrupt or the run diverged; {fix}")


def load_weights(model: torch.nn.Module, state: Mapping[str, torch.Tensor], where: Any, fix: str) -> None:
    """Load ``state`` into ``model`` (built from the checkpoint's hyperparameters) after checking it: the same
    tensor names, each of the model's shape and kind (floating or not), every float finite; one line naming the
    tensor instead of PyTorch's dump."""
    want = model.state_dict()
    missing, extra = sorted(set(want) - set(state)), sorted(set(state) - set(want))
    if missing or extra:
        what = (f"lacks {len(missing)} tensor(s) the model built from its hyperparameters has (e.g. {missing[0]!r})"
                if missing else f"has {len(extra)} tensor(s) that model does not (e.g. {extra[0]!r})")
        raise UserError(f"{where}: the weights {what}; {fix}")
    for name, w in want.items():
        t = state[name]
        if tuple(t.shape) != tuple(w.shape):
            raise UserError(f"{where}: tensor {name!r} has shape {tuple(t.shape)}, the model built from its "
                            f"hyperparameters needs {tuple(w.shape)}; {fix}")
        if t.is_floating_point() != w.is_floating_point():
            raise UserError(f"{where}: tensor {name!r} is {str(t.dtype).removeprefix('torch.')}, the model's is "
                            f"{str(w.dtype).removeprefix('torch.')}; {fix}")
    check_finite_state(state, where, fix)
    model.load_state_dict(state)


def _fits(value: Any, hint: Any) -> bool:
    """Whether a plain (JSON or checkpoint) value fits a parameter's type hint; hints it cannot judge pass."""
    import collections.abc
    import types
    import typing

    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, a) for a in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint in (bool, int, float):
        return _is(value, hint) and (hint is not bool or isinstance(value, bool))
    base = origin or hint
    if base is collections.abc.Callable or not isinstance(base, type):  # a partial's config; Any
        return True
    if base in (collections.abc.Sequence, list, tuple) and isinstance(value, str):
        return False  # "shading" is not a list of names
    return isinstance(value, base) or (base is tuple and isinstance(value, list))


def _hint_name(hint: Any) -> str:
    text = hint.__name__ if isinstance(hint, type) else str(hint)
    return text.replace("typing.", "").replace("collections.abc.", "")


def check_parameters(cls: type, config: Mapping[str, Any], where: Any, fix: str) -> None:
    """``config`` against ``cls``'s constructor: no parameter it lacks, none it requires missing, each value of
    its parameter's type; one line naming the hyperparameter."""
    import inspect
    import typing

    params = {k: q for k, q in inspect.signature(cls).parameters.items() if k != "self"}
    if not any(q.kind is q.VAR_KEYWORD for q in params.values()):
        unknown = sorted(set(config) - set(params))
        if unknown:
            raise UserError(f"{where}: hyper_parameters.{unknown[0]} is not a parameter of {cls.__name__}; {fix}")
    missing = [k for k, q in params.items() if q.default is q.empty and q.kind is q.POSITIONAL_OR_KEYWORD
               and k not in config]
    if missing:
        raise UserError(f"{where}: hyper_parameters.{missing[0]} is missing ({cls.__name__} requires it); {fix}")
    try:
        hints = typing.get_type_hints(cls.__init__)
    except Exception:  # noqa: BLE001 - a hint that does not resolve: the constructor judges the values
        hints = {}
    for key, value in config.items():
        if key in hints and not _fits(value, hints[key]):
            shown = json.dumps(value)[:40] if _is(value, float) or isinstance(value, str) else type(value).__name__
            raise UserError(f"{where}: hyper_parameters.{key} is {shown}, not of {cls.__name__}'s type for it "
                            f"({_hint_name(hints[key])}); {fix}")


def build_module(cls: type, config: Mapping[str, Any], state: Mapping[str, torch.Tensor], path: Any):
    """``cls(**config)`` with ``state`` loaded (:func:`load_weights`), both checked first (:func:`check_parameters`,
    :func:`check_hyper_parameters`): one line naming the checkpoint's file and the hyperparameter or tensor."""
    p = Path(str(path))
    folder = is_folder(p)
    where, weights = (p / CONFIG, p / WEIGHTS) if folder else (p, p)
    fix = (f"export the folder again: difareli-export <checkpoint>.ckpt {p}" if folder else
           "use the difareli version that wrote the checkpoint, or another checkpoint (an earlier step's)")
    check_hyper_parameters(dict(config), where, fix)  # a .ckpt's too: its resolution bounds a photo's relight
    check_parameters(cls, config, where, fix)
    try:
        model = cls(**config)
    except UserError as e:
        raise UserError(f"{where}: its hyperparameters do not build {cls.__name__} ({e}); {fix}") from None
    except (TypeError, ValueError, KeyError) as e:  # a value the hints allow but the constructor refuses
        raise UserError(f"{where}: its hyperparameters do not build {cls.__name__} ({type(e).__name__}: "
                        f"{str(e)[:160]}); {fix}") from None
    load_weights(model, state, weights, fix)
    return model
