"""`--help` of a console script opens with what the command does and three examples, then the command's own keys
(from its config file, with the file's comments), then the config groups it composes; not the whole composed config."""

from __future__ import annotations

import importlib
import sys

import pytest

# (console script, its module): the Hydra commands whose primary config carries a hydra.help header.
COMMANDS = [("difareli-relight", "relight"), ("difareli-train", "train"), ("difareli-synth", "synth"),
            ("difareli-demo", "demo"), ("difareli-preprocess", "preprocess"), ("difareli-ablate", "ablate"),
            ("difareli-teacher-pairs", "teacher_pairs"), ("difareli-bench-samplers", "bench_samplers"),
            ("difareli-multipie", "multipie")]


def _help(monkeypatch, capsys, script: str, module: str) -> str:
    main = importlib.import_module(f"difareli.cli.{module}").main
    monkeypatch.setattr(sys, "argv", [script, "--help"])
    monkeypatch.setenv("COLUMNS", "120")  # the listing wraps to the terminal: the same lines under any test runner
    with pytest.raises(SystemExit) as done:
        main()
    assert done.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("script,module", COMMANDS, ids=[c for c, _ in COMMANDS])
def test_help_opens_with_the_description_and_three_examples(script, module, monkeypatch, capsys):
    out = _help(monkeypatch, capsys, script, module)
    lines = out.splitlines()
    assert lines[0].startswith(f"{script}: ") and len(lines[0]) > len(script) + 20
    examples = lines.index("Examples:")
    assert examples < 6  # right under the description, not after the option listing
    shown = [line.strip() for line in lines[examples + 1:examples + 4]]
    # Three runnable lines of this command (the multipie one ends by scoring the store it made).
    assert sum(line.startswith(script + " ") for line in shown) >= 2 and len(shown) == 3
    assert "is powered by Hydra" not in out
    # The command's own keys and its groups, not the ~200-line composed config.
    assert len(lines) < 100
    assert "--cfg job" in out


def test_relight_help_lists_its_keys_then_only_the_groups_it_composes(monkeypatch, capsys):
    lines = _help(monkeypatch, capsys, "difareli-relight", "relight").splitlines()
    groups = next(i for i, line in enumerate(lines) if line.startswith("== Config groups"))
    keys = {line.split()[0]: i for i, line in enumerate(lines[:groups]) if line.startswith("  ") and "=" in line}
    # The command's own keys, with their defaults and the config file's comment, before the groups.
    assert "target.yaw=null" in keys and "image=null" in keys and "face=largest" in keys
    assert "rotate the input's own light about the up axis" in lines[keys["target.yaw=null"]]
    assert keys["image=null"] < keys["target.yaw=null"] < groups
    # A comment's continuation lines stay with their key: image= names the folder form on its wrapped lines.
    assert "folder" in " ".join(lines[keys["image=null"]:keys["face=largest"]])
    shown = {line.split("=")[0].strip() for line in lines[groups + 1:] if line.startswith("  ")}
    assert shown == {"sampler", "runtime", "paths", "local"}  # what relight.yaml composes, not trainer/model/...
    assert any(line.startswith("  sampler=default ") and "unipc" in line for line in lines)


def _scripts() -> dict[str, str]:
    import tomllib
    from pathlib import Path

    pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
    return tomllib.loads(pyproject.read_text())["project"]["scripts"]


@pytest.mark.parametrize("script", sorted(_scripts()))
def test_every_console_script_help_exits_0_and_prints_something(script, monkeypatch, capsys):
    module, function = _scripts()[script].split(":")
    entry = getattr(importlib.import_module(module), function)
    monkeypatch.setattr(sys, "argv", [script, "--help"])
    try:
        status = entry()
    except SystemExit as done:
        status = done.code
    assert status in (0, None)
    out = capsys.readouterr().out
    assert out.startswith(f"{script}: ") or out.startswith(f"usage: {script}"), out[:200]
