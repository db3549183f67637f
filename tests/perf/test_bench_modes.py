"""The benchmark scripts' modes say their precision: the runtime's default became ``auto`` (bf16 on a CPU with
native bf16), so a mode that left precision to the default and was labelled fp32 silently timed bf16 (caught in
``bench_official.py``, whose "fp32" row differed from the official code by 1.4 instead of ~1e-4)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from difareli.runtime.core import Runtime

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def modes(script: str) -> dict:
    """The script's ``MODES`` literal, read without importing the script (some set process-wide state)."""
    tree = ast.parse((SCRIPTS / script).read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "MODES" for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"{script} has no MODES")


@pytest.mark.parametrize("script", ["bench_official.py", "bench_runtime.py", "gpu_check.py"])
def test_every_mode_names_its_precision(script):
    table = modes(script)
    assert table and all("precision" in kw for kw in table.values()), table
    for name, kw in table.items():
        # "auto" only where the mode is named so; a bf16 name is bf16; every other mode picks fp32 or bf16 itself.
        assert (kw["precision"] == "auto") == (name == "auto"), (script, name, kw)
        assert kw["precision"] == "bf16" if "bf16" in name else kw["precision"] in ("fp32", "bf16", "auto"), (
            script, name, kw)
    assert Runtime(device="cpu", **table["fp32"]).precision == "fp32"
