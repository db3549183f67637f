"""The key listing of `--help` (difareli.cli.help): every key of a command's config file, with its default and the
file's comment on it, from the file alone."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

from difareli.cli.help import config_keys, format_keys, keys_help

CONF = Path(__file__).resolve().parents[2] / "conf"

TEXT = """\
# a file header: not any key's comment
defaults:
  - _self_
  - sampler: default   # not a key either

task_name: demo
# Above a key: its comment when the key has none of its own.
seed: 42
image: null              # a photo, or a folder
                         # or glob of photos
out: ${paths.output_dir} # where it writes
name: "a # not a comment"  # the real one
target:                  # exactly one of these
  yaw: null              # degrees
  sun: shadows
steps: [5, 10]
parts:                   # a block list, written back in one line
  - skin
  - "01"

hydra:
  help:
    app_name: demo       # not a key
"""


def test_keys_defaults_and_comments_from_the_text():
    keys = {k.name: k for k in config_keys(TEXT)}
    assert list(keys) == ["task_name", "seed", "image", "out", "name", "target.*", "target.yaw", "target.sun", "steps",
                          "parts"]
    assert keys["seed"].default == "42"
    assert keys["seed"].meaning == "Above a key: its comment when the key has none of its own."
    assert keys["image"].meaning == "a photo, or a folder or glob of photos"
    assert keys["out"].default == "${paths.output_dir}" and keys["out"].meaning == "where it writes"
    assert keys["name"].default == '"a # not a comment"' and keys["name"].meaning == "the real one"
    assert keys["target.*"].default is None and keys["target.*"].meaning == "exactly one of these"
    assert keys["target.yaw"].meaning == "degrees" and keys["target.sun"].meaning == ""
    assert keys["steps"].default == "[5, 10]" and keys["task_name"].meaning == ""
    assert keys["parts"].default == "[skin, '01']"  # "01" stays a string: [skin, 01] would read as 1


def test_the_listing_wraps_long_comments_under_their_column():
    text = "a: 1   # " + " ".join(["word"] * 40) + "\nlonger_key: 2\n"
    lines = format_keys(config_keys(text), width=60).splitlines()
    assert lines[0].startswith("  a=1") and all(len(line) <= 60 for line in lines)
    column = lines[0].index("word")
    assert all(line[:column].strip() == "" and line[column] == "w" for line in lines[1:-1])
    assert lines[-1].strip() == "longer_key=2"


def _covered(node, listed, prefix=""):
    """The dotted names of ``node`` the listing covers: a key listed whole (a flow mapping such as
    ``versions={shadow_map: null}``) or, for a block, each of its keys."""
    for key, value in node.items():
        name = f"{prefix}{key}"
        if name not in listed and isinstance(value, dict) and value:
            yield from _covered(value, listed, f"{name}.")
        else:
            yield name


@pytest.mark.parametrize("config", sorted(p.stem for p in CONF.glob("*.yaml")))
def test_every_key_of_every_command_config_is_listed_with_its_default(config):
    path = CONF / f"{config}.yaml"
    loaded = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    loaded = {k: v for k, v in loaded.items() if k not in ("defaults", "hydra")}
    listed = {k.name: k.default for k in config_keys(path.read_text()) if k.default is not None}
    assert sorted(listed) == sorted(_covered(loaded, listed))
    parser = OverridesParser.create()
    for name, default in listed.items():  # `name=<default>` typed on the command line gives the file's value
        value = loaded
        for part in name.split("."):
            value = value[part]
        typed = parser.parse_override(f"{name}={default}").value()
        assert (typed if not isinstance(typed, (list, dict)) else OmegaConf.to_container(OmegaConf.create(
            {"v": typed}))["v"]) == value, name
    # "$" reaches Hydra's string.Template doubled, so an interpolation in a default does not break the template.
    assert "$" not in keys_help(config).replace("$$", "")
