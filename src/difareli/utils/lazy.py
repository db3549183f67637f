"""Lazy package attributes (PEP 562): a package names where each public name lives, imported on first use."""

from __future__ import annotations

import importlib
from typing import Any, Callable


def lazy_attributes(package: str, homes: dict[str, str], namespace: dict[str, Any]
                    ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package`` whose names live in the submodules ``homes[name]``."""

    def __getattr__(name: str) -> Any:
        if name not in homes:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f".{homes[name]}", package), name)

    def __dir__() -> list[str]:
        return sorted(list(namespace) + list(homes))

    return __getattr__, __dir__
