"""An import of the package's own code inside a function is there to put off loading something (an optional
extra, torch and Lightning for a light command, the image metrics): one whose modules the file's top-level imports
load anyway defers nothing and hides a dependency from the file's head. Read statically from the syntax trees:
what the top-level imports load, followed through every module, against what each deferred import would load."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[2] / "src"


def _modules(src: Path, package: str = "difareli") -> dict[str, tuple[str, bool]]:
    """{module name: (source, is a package)} of every module under ``src/package``."""
    out = {}
    for p in sorted((src / package).rglob("*.py")):
        parts = p.relative_to(src).with_suffix("").parts
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (p.read_text(), is_pkg)
    return out


def _loads(node: ast.Import | ast.ImportFrom, module: str, is_pkg: bool, known: set[str]) -> set[str]:
    """The package's modules an import statement runs: the module named, its parent packages, and a submodule
    named in ``from X import sub``."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        base = node.module or ""
        if node.level:
            here = module.split(".") if is_pkg else module.split(".")[:-1]
            here = here[: len(here) - node.level + 1]
            base = ".".join(here + ([base] if base else []))
        names = [base] + [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in known]
    out = set()
    for name in names:
        parts = name.split(".")
        out.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))
    return out & known


def _split(tree: ast.Module) -> tuple[list, list]:
    """(imports run when the module is imported, imports inside functions); ``if TYPE_CHECKING:`` blocks are
    neither."""
    top, deferred = [], []

    def visit(nodes, in_function):
        for n in nodes:
            if isinstance(n, ast.If) and "TYPE_CHECKING" in ast.unparse(n.test):
                continue
            if isinstance(n, (ast.Import, ast.ImportFrom)):
                (deferred if in_function else top).append(n)
            elif isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(ast.iter_child_nodes(n), True)
            else:
                visit(ast.iter_child_nodes(n), in_function)

    visit(tree.body, False)
    return top, deferred


def free_deferred(modules: dict[str, tuple[str, bool]]) -> list[str]:
    """``file:line: import`` for each function-level import of the package's own code that loads nothing the
    module's top-level imports (followed transitively) have not loaded already."""
    known = set(modules)
    trees = {m: ast.parse(src) for m, (src, _) in modules.items()}
    direct, deferred = {}, {}
    for m, tree in trees.items():
        top, later = _split(tree)
        is_pkg = modules[m][1]
        direct[m] = set().union(*[_loads(n, m, is_pkg, known) for n in top]) if top else set()
        deferred[m] = [(n, _loads(n, m, is_pkg, known)) for n in later]
    closure: dict[str, set[str]] = {}

    def loaded(m: str) -> set[str]:
        if m not in closure:
            parts = m.split(".")
            seen, todo = set(), [".".join(parts[:i]) for i in range(1, len(parts) + 1)]
            while todo:
                x = todo.pop()
                if x not in seen:
                    seen.add(x)
                    todo.extend(direct.get(x, ()))
            closure[m] = seen
        return closure[m]

    return [f"{m}:{n.lineno}: {ast.unparse(n)}" for m in sorted(deferred) for n, wants in deferred[m]
            if wants and wants <= loaded(m)]


def test_no_deferred_import_of_the_package_defers_nothing():
    free = free_deferred(_modules(SRC))
    assert free == [], "imports inside functions whose modules the file's top already loads; move them to the " \
                       "top of the file:\n" + "\n".join(free)


def test_the_check_finds_a_deferred_import_that_defers_nothing_and_spares_one_that_does(tmp_path):
    pkg = tmp_path / "difareli"
    (pkg / "sub").mkdir(parents=True)
    for name, text in {
        "__init__.py": "",
        "low.py": "X = 1\n",
        "heavy.py": "import torch  # noqa\n",
        "sub/__init__.py": "from difareli import low\n",
        "sub/user.py": ("from difareli.sub import low as _l  # noqa\n\n\ndef f():\n    from difareli.low import X\n\n"
                        "    return X\n\n\ndef g():\n    from difareli import heavy\n\n    return heavy\n\n\n"
                        "def h():\n    from .. import low\n\n    return low\n"),
    }.items():
        (pkg / name).write_text(text)
    assert free_deferred(_modules(tmp_path)) == ["difareli.sub.user:5: from difareli.low import X",
                                                 "difareli.sub.user:17: from .. import low"]
