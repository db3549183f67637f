"""A checkpoint named, read and built into its module, for notebooks and CLIs: only the package and the file.

A checkpoint is a shipped name (:mod:`difareli.checkpoints.zoo`: its folder when it has one), a ``.ckpt`` file
(``torch.load`` with ``weights_only=True``) or a weights folder written by ``difareli-export`` (``model.safetensors``
+ ``config.json``: no pickle at all); :func:`resolve` turns the name or path into the file or folder, and
:mod:`difareli.checkpoints.format` reads it (translating older formats). It records the module class that wrote it:
:func:`load_checkpoint` finds that class among the registered ones (``difareli.lit``'s models register themselves
as they are defined, :func:`register`; the package's root hands down, once, how to load them, :func:`provide`, so
the loader never imports a layer above its own by a name) and builds it from the plain hyperparameters, each
checked (:func:`build_module`). Importing this module loads neither torch nor Lightning: a command that reads no
checkpoint pays for neither.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from difareli.checkpoints.format import (CONFIG, MODULE_KEY, WEIGHTS, check_hyper_parameters, folder_problem,
                                         is_folder, json_is, load_torch_file, read_folder, refuse_official,
                                         training_resolution, upgrade_checkpoint)
from difareli.checkpoints import zoo
from difareli.errors import UserError, UserFileNotFoundError, check_file

if TYPE_CHECKING:
    import lightning as L
    import torch

#: Registered classes by the name a checkpoint records.
MODULE_CLASSES: dict[str, type] = {}
_PROVIDERS: list[Callable[[], object]] = []


def register(cls: type) -> type:
    """Let checkpoints that record ``cls`` (by its module and qualified name) load into it."""
    MODULE_CLASSES[f"{cls.__module__}.{cls.__qualname__}"] = cls
    return cls


def provide(load: Callable[[], object]) -> None:
    """``load()`` registers classes (imports the modules that define them); called when a name is first missing."""
    if load not in _PROVIDERS:
        _PROVIDERS.append(load)


def module_class(name: str) -> type:
    """The registered class a checkpoint names; a UserError naming it where nothing registered it."""
    if not isinstance(name, str) or not name.startswith("difareli."):
        raise UserError(f"checkpoint names module class {name!r}; only classes under 'difareli.' load")
    while name not in MODULE_CLASSES and _PROVIDERS:
        _PROVIDERS.pop(0)()
    if name in MODULE_CLASSES:
        return MODULE_CLASSES[name]
    raise UserError(f"checkpoint names module class {name!r}, which this difareli version does not have (no model "
                    "registers that name); it was written by another version of difareli: load it with that version")


def resolve(checkpoint: str | Path, key: str = "checkpoint", prefer_folder: bool = False) -> Path:
    """The file or weights folder of a checkpoint given as a path or as a shipped name (a path of that name wins);
    a shipped name is its ``.ckpt`` (what a caller that ``torch.load`` s the file needs) or, with ``prefer_folder``
    (``load_checkpoint``), its weights folder when it has one. A missing one is a FileNotFoundError naming the
    input and the shipped names."""
    path = Path(str(checkpoint)).expanduser()
    if path.is_file():
        return check_file(path, key)
    if is_folder(path):
        return path
    problem = folder_problem(path)  # a weights folder missing one of its files: say which, not "is a folder"
    if problem:
        raise UserFileNotFoundError(problem)
    shipped = "/" not in str(checkpoint) and str(checkpoint) not in ("", ".", "..")
    if shipped and prefer_folder and is_folder(zoo.SHIPPED_DIR / str(checkpoint)):
        return zoo.SHIPPED_DIR / str(checkpoint)
    if shipped and (zoo.SHIPPED_DIR / f"{checkpoint}.ckpt").is_file():
        return zoo.SHIPPED_DIR / f"{checkpoint}.ckpt"
    if shipped and is_folder(zoo.SHIPPED_DIR / str(checkpoint)):
        return zoo.SHIPPED_DIR / str(checkpoint)
    try:
        return check_file(path, key)
    except FileNotFoundError as e:
        raise UserFileNotFoundError(f"{e} (<run>/checkpoints/last.ckpt, or a weights folder of difareli-export), or "
                                    f"the name of a shipped checkpoint: "
                                    f"{', '.join(zoo.available()) or 'none shipped'}") from None


@dataclass
class LoadedCheckpoint:
    """A model ready for inference plus what it was trained with."""

    model: L.LightningModule
    config: dict[str, Any]
    stats: dict[str, torch.Tensor]
    global_step: int

    @property
    def resolution(self) -> int | None:
        """The image size (px) it was trained at (:func:`~difareli.checkpoints.format.training_resolution`)."""
        return training_resolution(self.config)

    @classmethod
    def of(cls, model: L.LightningModule, config: Mapping[str, Any], global_step: int = 0) -> "LoadedCheckpoint":
        """``model`` with its hyperparameters ``config`` as a loaded checkpoint: the config as inference reads it
        (``compile`` dropped: inference never compiles implicitly) and the normalisation statistics it holds."""
        import torch

        config = _inference_config(config)
        raw = config.get("nonspatial_stats") or {}
        stats = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in raw.items()}
        return cls(model=model, config=config, stats=stats, global_step=int(global_step))

    @classmethod
    def of_module(cls, module: L.LightningModule, global_step: int = 0) -> "LoadedCheckpoint":
        """A module already in memory (the one in training, an untrained one) as a loaded checkpoint, its own
        hyperparameters the config; nothing is copied."""
        return cls.of(module, getattr(module, "hparams", None) or {}, global_step)


def read_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The checkpoint dict, translated to the current format, of ``path``: a .ckpt file (``torch.load(weights_only=
    True)``), a weights folder (safetensors + JSON, no pickle) or a shipped name such as ``difareli_pp-synth64``
    (its weights folder when shipped, else its .ckpt)."""
    path = resolve(path, prefer_folder=True)  # a file, a folder, or a shipped name
    if is_folder(path):
        return upgrade_checkpoint(read_folder(path, map_location), path)
    ckpt = load_torch_file(path, "checkpoint", map_location)  # torch.load(weights_only=True), errors name the file
    if "hyper_parameters" not in ckpt or "state_dict" not in ckpt:
        refuse_official(ckpt, path)  # the authors' ImgCond/ImgEncoder .pt: a message naming the import command
        raise UserError(f"{path} is not a difareli Lightning checkpoint (no hyper_parameters/state_dict)")
    return upgrade_checkpoint(ckpt, path)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> LoadedCheckpoint:
    """Load a checkpoint with ``torch.load(weights_only=True)`` into the module class it records.

    The weights are the EMA weights when training used the EMA callback (Lightning stores the average in
    ``state_dict``); the config is the model's plain hyperparameters; stats are the non-spatial
    normalisation statistics of the training split (as tensors).
    """
    ckpt = read_checkpoint(path, map_location)
    config = _inference_config(ckpt["hyper_parameters"])
    model = build_module(module_class(ckpt[MODULE_KEY]), config, ckpt["state_dict"], path)
    model.eval().requires_grad_(False)
    return LoadedCheckpoint.of(model.to(map_location), config, ckpt.get("global_step", 0))


def _inference_config(hparams: Mapping[str, Any]) -> dict[str, Any]:
    # Inference never compiles implicitly: a model trained with compile=true is built without it.
    return {k: v for k, v in dict(hparams).items() if k != "compile"}


def check_resume(ckpt_path: Any, model: Any, ckpt: Mapping[str, Any] | None = None) -> None:
    """Resuming ``model`` from ``ckpt_path``: if state-dict keys or shapes differ, raise a UserError listing
    the differing hyperparameters (or tensors), instead of PyTorch's size-mismatch dump. ``ckpt``: the
    checkpoint dict when the caller has already read it."""
    ckpt = load_torch_file(ckpt_path, "ckpt_path") if ckpt is None else ckpt
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise UserError(f"ckpt_path={ckpt_path} is not a Lightning checkpoint (no state_dict)")
    have = {k: tuple(v.shape) for k, v in ckpt["state_dict"].items() if hasattr(v, "shape")}
    want = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    bad = sorted(k for k in set(have) | set(want) if have.get(k) != want.get(k))
    if not bad:
        return
    saved = dict(ckpt.get("hyper_parameters") or {})
    now = dict(getattr(model, "hparams", {}) or {})
    diff = [f"{k}: checkpoint {saved.get(k)!r}, config {now.get(k)!r}" for k in sorted(set(saved) | set(now))
            if k != "compile" and saved.get(k) != now.get(k)]
    listed = "; ".join(diff[:8]) if diff else f"tensors {', '.join(bad[:5])}"
    raise UserError(f"ckpt_path={ckpt_path} does not match this model config ({len(bad)} tensors differ): "
                    f"{listed}\nresume with the model config it was trained with (see <run>/.hydra/config.yaml)")


# ---------------------------------------------------------------------------------------------- a module built
def check_finite_state(state: Mapping[str, Any], where: Any, fix: str) -> None:
    """Every floating tensor of ``state`` is finite; the first that is not is a UserError naming it (the weights
    themselves are bad, whatever precision a run would use)."""
    import torch

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
        return json_is(value, hint) and (hint is not bool or isinstance(value, bool))
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
            shown = json.dumps(value)[:40] if json_is(value, float) or isinstance(value, str) else type(value).__name__
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
