"""`--help` of a console script opens with what the command does and three examples, then a short option listing
(the config groups or the command's own keys), not the whole composed config."""

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
    # The listing stays short: the groups or the command's own keys, not the ~200-line composed config.
    assert len(lines) < 80
    assert "--cfg job" in out


def test_relight_help_lists_the_groups_not_the_composed_config(monkeypatch, capsys):
    out = _help(monkeypatch, capsys, "difareli-relight", "relight")
    assert "sampler: " in out and "trainer: " in out  # the group listing
    assert "checkpoint: ???" not in out and "mean_matching:" not in out  # the composed config's keys
