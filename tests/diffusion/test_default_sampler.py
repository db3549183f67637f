"""One default sampler: every relighting command, the app, the notebook and a bare ``Relighter`` use
``PRESETS["default"]``, and every shipped diffusion checkpoint's card was benchmarked with it, so a command with no
sampler options reproduces the card's rows."""

from __future__ import annotations

import json

import pytest

from difareli.checkpoints import zoo
from difareli.diffusion import DEFAULT_SAMPLER, PRESETS, SamplerSpec
from difareli.lit import load_checkpoint

from tests.helpers import CONF, compose_train

DEFAULT = PRESETS[DEFAULT_SAMPLER]
ROOT = CONF.parent  # conf/ sits at the top of the repository


@pytest.mark.parametrize("command", ["relight", "video", "benchmark", "ablate", "demo", "teacher_pairs"])
def test_every_relighting_command_defaults_to_the_default_sampler(command, tmp_path):
    cfg = compose_train(tmp_path, [], config_name=command)
    assert SamplerSpec.from_config(cfg.sampler) == DEFAULT


def test_the_default_is_a_real_sampler_and_overrides_still_reach_it(tmp_path):
    assert DEFAULT.name in ("ddim", "dpm_solver", "dpm_solver_pp", "unipc") and DEFAULT.steps >= 1
    cfg = compose_train(tmp_path, ["sampler=ddim", "sampler.steps=7"], config_name="benchmark")
    assert SamplerSpec.from_config(cfg.sampler) == SamplerSpec("ddim", steps=7)


def test_app_and_notebook_start_from_the_default():
    from difareli.app.service import DEFAULT as APP_DEFAULT

    assert APP_DEFAULT == DEFAULT
    nb = json.loads((ROOT / "notebooks" / "relight_from_checkpoint.ipynb").read_text())
    code = "".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
    assert 'os.environ.get("DIFARELI_SAMPLER", "default")' in code
    assert "as_spec(SAMPLER, steps=STEPS)" in code


def test_a_relighter_without_a_sampler_uses_the_default():
    from difareli.relight.relighter import Relighter

    name = next(n for n in zoo.available() if load_checkpoint(n).config.get("name") != "student")
    assert Relighter(name, device="cpu").spec == DEFAULT


@pytest.mark.parametrize("name", zoo.available())
def test_every_shipped_card_was_benchmarked_with_the_default(name):
    """The card's sampler fact names the default preset's sampler and steps (a one-pass student: one pass)."""
    from difareli.checkpoints.loading import read_checkpoint

    loaded = load_checkpoint(name)
    sampler = read_checkpoint(name).get("model_card", {}).get("sampler")
    assert sampler is not None, f"{name}: the card records no sampler fact (re-release it with release_reference.py)"
    one_pass = loaded.config.get("name") == "student"
    assert sampler == ("one network pass" if one_pass else f"{DEFAULT.name}-{DEFAULT.steps}")
