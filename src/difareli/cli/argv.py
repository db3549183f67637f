"""The argument handling of the two commands that take plain arguments rather than a Hydra config
(``difareli-export``, ``difareli-import-checkpoint``), kept free of heavy imports so ``--help`` is instant."""

from __future__ import annotations

import sys


def argv_or_help(argv: list[str] | None, doc: str | None) -> list[str] | None:
    """The command's arguments (``sys.argv[1:]`` by default), or None after printing its help (``doc``) for no
    arguments, ``-h`` or ``--help``."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(doc)
        return None
    return argv
