"""The layers contract (pyproject.toml ``[tool.importlinter]``) holds on the package, and fails the moment a module
imports from a layer above its own, or the app imports the relighter past the answer layer: checked on a copy of the
package with one such import added."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
LINT = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")

pytestmark = pytest.mark.skipif(LINT is None, reason="import-linter not installed (pip install -e '.[dev]')")


def _lint(src: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(src)}
    return subprocess.run([LINT, "--config", str(REPO / "pyproject.toml"), "--no-cache"], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def _copy(tmp_path: Path) -> Path:
    src = tmp_path / "src"
    shutil.copytree(REPO / "src" / "difareli", src / "difareli",
                    ignore=shutil.ignore_patterns("__pycache__", "*.ckpt", "static"))
    return src


def test_the_package_keeps_its_layers(tmp_path):
    out = _lint(_copy(tmp_path), tmp_path)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "2 kept, 0 broken" in out.stdout


@pytest.mark.parametrize("low, high", [("data/store.py", "difareli.relight.relighter"),
                                       ("utils/fileio.py", "difareli.data.store"),
                                       ("errors.py", "difareli.diffusion.spec"),
                                       ("app/service.py", "difareli.relight.relighter")])
def test_an_import_that_climbs_breaks_the_contract(tmp_path, low, high):
    src = _copy(tmp_path)
    path = src / "difareli" / low
    path.write_text(path.read_text() + f"\n\ndef _climb():\n    import {high}  # noqa: F401\n")
    out = _lint(src, tmp_path)
    assert out.returncode != 0
    assert "BROKEN" in out.stdout and high in out.stdout, out.stdout[-3000:]
