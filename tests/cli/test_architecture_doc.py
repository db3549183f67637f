"""The floor list of docs/architecture.md and the README's list of layers are the layers contract that
``lint-imports`` checks (pyproject.toml ``[tool.importlinter]``), floor for floor."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def contract_layers() -> list[str]:
    """The contract's layers, highest first (``"a | b"``: siblings)."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    (contract,) = [c for c in config["tool"]["importlinter"]["contracts"] if c["type"] == "layers"]
    return contract["layers"]


def doc_floors(text: str) -> list[str]:
    """The floors of the code block under ``## Floors and homes``: each unindented line's name, before its
    description (two or more spaces)."""
    block = text.split("## Floors and homes", 1)[1].split("```", 2)[1]
    return [re.split(r"\s{2,}", line)[0].strip() for line in block.splitlines() if line and not line[0].isspace()]


def readme_layers(text: str) -> list[str]:
    """The README's "The package's folders are its layers (...; lowest first)", highest first, ``a / b`` as
    ``a | b``."""
    inside = re.search(r"folders are its\s+layers \((.*?), lowest first\)", text, re.S).group(1)
    names = [part.strip().replace("`", "").replace(" / ", " | ") for part in re.split(r",\s+", inside)]
    return names[::-1]


def test_the_architecture_doc_lists_the_contracts_floors():
    assert doc_floors((REPO / "docs" / "architecture.md").read_text()) == contract_layers()


def test_the_readme_lists_the_contracts_folders():
    # The root modules (configs, errors, hardware) are files, not folders: the README names the folders.
    root = {"configs", "errors | hardware"}
    assert readme_layers((REPO / "README.md").read_text()) == [x for x in contract_layers() if x not in root]


def test_the_parsers_see_a_floor_moved():
    doc = "## Floors and homes\n\n```\ncli       entry points\nrelight | synth    relighting |\n" \
          "                   SynthFaces\ndata      records\n```\n"
    assert doc_floors(doc) == ["cli", "relight | synth", "data"]
    readme = "The package's folders are its\nlayers (`data`, `relight` / `synth`, `cli`, lowest first); ..."
    assert readme_layers(readme) == ["cli", "relight | synth", "data"]
