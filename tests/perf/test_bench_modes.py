"""Runtime modes have one spelling, ``<precision>[+compile][+cuda_graphs]`` (:meth:`Runtime.from_mode`), shared by
the benchmark scripts: before, three scripts kept their own tables and "compile" meant fp32 in two and bf16 in one
(and a mode that left precision to the runtime's ``auto`` default, labelled fp32, silently timed bf16)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from difareli.errors import UserError
from difareli.runtime.core import Runtime

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


@pytest.mark.parametrize("mode, precision, compile_, graphs", [
    ("fp32", "fp32", False, False), ("bf16", "bf16", False, False), ("fp32+compile", "fp32", True, False),
    ("bf16+compile", "bf16", True, False), ("bf16+cuda_graphs", "bf16", False, True),
    ("bf16+compile+cuda_graphs", "bf16", True, True)])
def test_a_mode_name_says_its_precision_and_round_trips(mode, precision, compile_, graphs):
    rt = Runtime.from_mode(mode, "cpu")
    assert (rt.precision, rt.compile, rt.cuda_graphs) == (precision, compile_, graphs)
    assert rt.mode() == mode


def test_auto_resolves_to_a_named_precision():
    assert Runtime.from_mode("auto", "cpu").mode() in ("fp32", "bf16")


@pytest.mark.parametrize("bad", ["compile", "cuda_graphs", "fp32+fast", "bf16+compile+compile", "", "fp64"])
def test_a_mode_without_its_precision_is_refused(bad):
    with pytest.raises(UserError, match="<precision>"):
        Runtime.from_mode(bad, "cpu")


def _literal(script: str, name: str):
    for node in ast.parse((SCRIPTS / script).read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == name for t in node.targets):
            return ast.literal_eval(node.value)
    return None


@pytest.mark.parametrize("script", ["bench_official.py", "bench_runtime.py", "gpu_check.py"])
def test_scripts_keep_no_mode_table_of_their_own(script):
    table = _literal(script, "MODES")
    assert not isinstance(table, dict), f"{script} defines its own MODES mapping"
    for mode in table or ():  # gpu_check's list of names: each one parses
        Runtime.from_mode(mode, "cpu")
    assert "Runtime.from_mode(" in (SCRIPTS / script).read_text()
