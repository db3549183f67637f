"""``--help`` of every Hydra command: its own keys first, read from its primary config file (name, default and
the file's comment on it), then the config groups it composes with their options.

The template is ``conf/hydra/help/difareli.yaml``; it calls the two resolvers registered here, so the listing has
one source, the config files themselves, and no command keeps a list of its keys by hand.
"""

from __future__ import annotations

import re
import shutil
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import yaml
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from difareli.configs import CONFIG_DIR

#: Top-level blocks of a primary config that are not the command's keys.
_NOT_KEYS = ("defaults", "hydra")
_KEY = re.compile(r"^(\s*)([A-Za-z_][\w-]*)\s*:(?:\s+|$)(.*)$")


@dataclass(frozen=True)
class Key:
    """One entry of the listing: a dotted key (``target.yaw``, or ``target.*`` for a block), the default as
    written in the file (``key=<default>`` on the command line), and the file's comment on it."""

    name: str
    default: str | None
    meaning: str


def _split_comment(line: str) -> tuple[str, str | None, int]:
    """``(body, comment, column)``: a YAML comment starts at a ``#`` outside quotes that opens the line or follows
    a space (column -1: none)."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip(), line[i + 1:].strip(), i
    return line.rstrip(), None, -1


def _render(value: Any) -> str:
    """A loaded value written back as a command-line override would spell it."""
    if value is None or isinstance(value, bool):
        return {None: "null", True: "true", False: "false"}[value]
    if isinstance(value, list):
        return "[" + ", ".join(_render(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_render(v)}" for k, v in value.items()) + "}"
    text = str(value)
    return text if isinstance(value, str) and yaml.safe_load(text) == value else repr(value)


def config_keys(text: str) -> list[Key]:
    """The keys of a primary config's text with their comments: the comment after a key (and the comment lines
    under it aligned with that comment), or else the comment lines right above it."""
    loaded = yaml.safe_load(text) or {}
    found: list[tuple[str, str | None, list[str]]] = []
    parents: list[tuple[int, str]] = []  # (indent, name) of the enclosing blocks
    above: list[str] = []  # comment lines right above the next key
    last: tuple[int, list[str]] | None = None  # (column of the last key's comment, its lines)
    skipping = False
    for line in text.splitlines():
        body, comment, column = _split_comment(line)
        indent = len(line) - len(line.lstrip())
        if not line.strip():
            above, last = [], None
            continue
        if not body:  # a comment line: it goes on the last key's comment, or above the next key
            if last is not None and column == last[0]:
                last[1].append(comment or "")
            else:
                above, last = above + [comment or ""], None
            continue
        match = _KEY.match(body)
        if skipping and (indent > 0 or not match):
            continue
        skipping, name = False, match.group(2) if match else None
        if name is None or (indent == 0 and name in _NOT_KEYS):
            skipping, above, last = name is not None, [], None
            continue
        while parents and parents[-1][0] >= indent:
            parents.pop()
        path = [p for _, p in parents] + [name]
        lines = [comment] if comment is not None else above
        node = _lookup(loaded, path)
        block = isinstance(node, dict) and not match.group(3).strip()
        default = None if block else (match.group(3).strip() or _render(node))
        found.append((".".join(path) + (".*" if block else ""), default, lines))
        last, above = ((column, lines) if comment is not None else None), []
        if block:
            parents.append((indent, name))
    return [Key(name, default, " ".join(" ".join(lines).split())) for name, default, lines in found]


def _lookup(tree: Any, path: list[str]) -> Any:
    for part in path:
        tree = tree.get(part) if isinstance(tree, dict) else None
    return tree


def _width() -> int:
    return min(120, shutil.get_terminal_size((120, 24)).columns)


def _columns(rows: list[tuple[str, str]], width: int) -> str:
    """``left  right`` rows, the right column wrapped under itself (a long left part puts it on the next line)."""
    col = min(max((len(left) for left, _ in rows), default=0) + 2, 40)
    out = []
    for left, right in rows:
        wrapped = textwrap.wrap(right, max(width - col, 30)) or [""]
        if len(left) + 2 > col:
            out.append(left)
            out.extend(" " * col + w for w in wrapped if w)
        else:
            out.append(left.ljust(col) + wrapped[0])
            out.extend(" " * col + w for w in wrapped[1:])
    return "\n".join(line.rstrip() for line in out)


def format_keys(keys: list[Key], width: int | None = None) -> str:
    # A block's own line only where the file says something about it; its keys follow, dotted.
    rows = [(f"  {k.name}" if k.default is None else f"  {k.name}={k.default}", k.meaning) for k in keys
            if k.default is not None or k.meaning]
    return _columns(rows, width or _width())


def format_groups(choices: Mapping[str, str | None], options, width: int | None = None) -> str:
    """``group=choice`` and the group's options, for the groups the command composes (Hydra's own left out)."""
    rows = []
    for group in sorted(choices):
        if group == "hydra" or group.startswith("hydra/"):
            continue
        folder = group.split("@")[0]  # model@variant: the model group, placed at `variant`
        found = sorted(options(folder))
        rows.append((f"  {group}={choices[group] or 'null'}",
                     ", ".join(found) if found else f"none shipped (your own conf/{folder}/<name>.yaml)"))
    return _columns(rows, width or _width())


def _group_options(group: str) -> list[str]:
    hydra = GlobalHydra.instance()
    return hydra.config_loader().get_group_options(group) if hydra.is_initialized() else []


def _escape(text: str) -> str:
    # Hydra fills the template with string.Template: a "$" of ours (${paths.output_dir}) must reach it as "$$".
    return text.replace("$", "$$")


def keys_help(config_name: str) -> str:
    """``${difareli_help_keys:<config name>}``: the listing of ``conf/<config name>.yaml``'s keys."""
    path = Path(CONFIG_DIR) / f"{config_name}.yaml"
    return _escape(format_keys(config_keys(path.read_text())))


def groups_help(choices: DictConfig | Mapping[str, Any]) -> str:
    """``${difareli_help_groups:${hydra.runtime.choices}}``: the groups this command composes."""
    plain = OmegaConf.to_container(choices) if isinstance(choices, DictConfig) else dict(choices)
    return _escape(format_groups(plain, _group_options))


def register() -> None:
    """Register the two resolvers the help template calls (idempotent)."""
    OmegaConf.register_new_resolver("difareli_help_keys", keys_help, replace=True)
    OmegaConf.register_new_resolver("difareli_help_groups", groups_help, replace=True)
