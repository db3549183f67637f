"""The module classes a checkpoint may name, registered from above: a checkpoint records its class by name
(``package.module.Class``) and the loader looks it up here; it never imports a layer above its own by a name.
``difareli.lit``'s models register themselves as they are defined (:func:`register`); the package's root hands
down, once, how to load them (:func:`provide`: ``difareli/__init__.py`` imports ``difareli.lit`` when a checkpoint
first names a class, so a command that reads none loads no Lightning)."""

from __future__ import annotations

from collections.abc import Callable

from difareli.errors import UserError

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
