"""A bounded dict: the caches of a long-lived process (the app's, a relighter's) keep at most a given number of
entries, the least recently used dropped first."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

from difareli.errors import UserError


class LRU(OrderedDict):
    """A dict keeping at most ``size`` entries: reading or writing one makes it the newest, a write beyond
    ``size`` drops the oldest. Usable wherever a plain dict cache is (``in``, ``[]``, assignment)."""

    def __init__(self, size: int):
        super().__init__()
        if int(size) < 1:
            raise UserError(f"cache size {size!r} must be >= 1")
        self.size = int(size)

    def __getitem__(self, key: Any) -> Any:
        value = super().__getitem__(key)
        self.move_to_end(key)
        return value

    def get(self, key: Any, default: Any = None) -> Any:
        return self[key] if key in self else default

    def __setitem__(self, key: Any, value: Any) -> None:
        super().__setitem__(key, value)
        self.move_to_end(key)
        while len(self) > self.size:
            self.popitem(last=False)
