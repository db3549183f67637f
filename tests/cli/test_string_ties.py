"""Ties the layers contract cannot see: an import by a string. A string in the package that names one of its
modules (``"difareli.relight.targets:render_light"``, ``"difareli.lit.diffusion.DiffusionModule"``) is an import
the moment something resolves it; it may name only the module's own layer or one below (pyproject.toml's
``[tool.importlinter]`` order), and every call that imports by a computed name is one of the few listed here, each
with what bounds it. Read statically from the syntax trees; checked on a copy with one climbing string added."""

from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SRC = REPO / "src" / "difareli"
NAME = re.compile(r"difareli(\.[A-Za-z_]\w*)+(:[A-Za-z_]\w*)?")
DYNAMIC = {"import_module", "get_class", "__import__", "get_method", "get_object"}
#: Calls that import by a computed name, and why each stays within the house's order.
ALLOWED = {
    "utils/lazy.py": "a package's own submodules (relative to the package that asks)",
    "perf/measure.py": "a config's _target_ (conf/ is above every layer: the command that reads it chose it)",
    "evaluation/baselines.py": "a method config's _target_ (conf/method/*.yaml, chosen by the command)",
}
#: Strings that name a class above their file as data, not as an import: looked up among the registered classes
#: (checkpoints.loading.MODULE_CLASSES, which difareli.lit fills), never imported.
NAMED_AS_DATA = {"checkpoints/format.py": "the module class that checkpoints older than the module key recorded"}


def layers() -> dict[str, int]:
    """Each top-level package (and root module) -> its layer's rank, 0 the highest."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    (contract,) = [c for c in config["tool"]["importlinter"]["contracts"] if c["type"] == "layers"]
    return {name.strip(): rank for rank, layer in enumerate(contract["layers"]) for name in layer.split("|")}


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def climbing_strings(src: Path) -> list[str]:
    """``file:line: 'name'`` for each string (not a docstring) naming a module of the package above the file's
    layer."""
    rank = layers()
    bad = []
    for path in sorted(src.rglob("*.py")):
        rel = path.relative_to(src)
        here = None if str(rel) in NAMED_AS_DATA else rank.get(rel.parts[0].removesuffix(".py"))
        tree = ast.parse(path.read_text())
        skip = _docstrings(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
                m = NAME.fullmatch(node.value.strip())
                target = rank.get(m.group(0).split(".")[1].split(":")[0]) if m else None
                if here is not None and target is not None and target < here:
                    bad.append(f"{rel}:{node.lineno}: {node.value!r}")
    return bad


def dynamic_imports(src: Path) -> set[str]:
    """The files that import by a computed name (``importlib.import_module``, Hydra's ``get_class``, ...)."""
    out = set()
    for path in sorted(src.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                f = node.func
                name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
                if name in DYNAMIC:
                    out.add(str(path.relative_to(src)))
    return out


def test_no_string_names_a_module_above_its_own():
    assert climbing_strings(SRC) == []


def test_every_import_by_a_computed_name_is_listed():
    assert dynamic_imports(SRC) <= set(ALLOWED), sorted(dynamic_imports(SRC) - set(ALLOWED))


@pytest.mark.parametrize("low, name", [("data/encodings.py", "difareli.relight.targets:render_light"),
                                       ("render/retarget.py", "difareli.lit.diffusion.DiffusionModule"),
                                       ("checkpoints/loading.py", "difareli.lit.student.StudentModule")])
def test_a_climbing_string_is_found(tmp_path, low, name):
    import shutil

    copy = tmp_path / "difareli"
    shutil.copytree(SRC, copy, ignore=shutil.ignore_patterns("__pycache__", "*.ckpt", "*.safetensors", "static"))
    path = copy / low
    path.write_text(path.read_text() + f"\n\nTIE = {name!r}\n")
    assert [line.split(": ", 1)[1] for line in climbing_strings(copy)] == [repr(name)]
    loader = "\n\ndef _load(n):\n    import importlib\n\n    return importlib.import_module(n)\n"
    path.write_text(path.read_text() + loader)
    assert low in dynamic_imports(copy) - set(ALLOWED)
