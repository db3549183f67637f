"""difareli-synth: config composition, validation naming the key, resume message, preview."""

import os
import subprocess
import sys

import pytest
from hydra import compose, initialize_config_dir

from difareli.cli import synth as cli
from difareli.configs import CONFIG_DIR
from difareli.synth.config import ConfigError


def _cfg(overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONFIG_DIR)):
        return compose(config_name="synth", overrides=overrides)


@pytest.mark.parametrize("key,value", [("resolution", 8), ("subjects", 0), ("lights", -1), ("workers", 0)])
def test_bad_values_name_the_key(key, value, tmp_path):
    cfg = _cfg([f"out_dir={tmp_path}", f"{key}={value}"])
    with pytest.raises(ConfigError, match=rf"^{key}={value}"):
        cli.validate(cfg)
    assert not (tmp_path / "store.json").exists()


def test_missing_out_dir_and_unknown_key():
    with pytest.raises(ConfigError, match="out_dir"):
        cli.validate(_cfg([]))
    with pytest.raises(Exception, match="subject"):
        _cfg(["out_dir=x", "subject=3"])  # struct mode: typos are errors


def test_run_then_nothing_to_do(tmp_path, capsys):
    out = tmp_path / "sf"
    cfg = _cfg([f"out_dir={out}", "subjects=3", "lights=2", "resolution=24", "workers=1", "preview.cell=48",
                "inputs=estimated_light"])  # v3 needs the photo estimators (test_synth_v3 covers it)
    report = cli.run(cfg)
    text = capsys.readouterr().out
    assert report.written == 6 and "wrote 6 records" in text and "images/s" in text
    assert (out / "preview.png").is_file()
    import imageio.v3 as iio

    sheet = iio.imread(out / "preview.png")
    # 3 subjects x 3 rows (image, shading, shadow) of 48px cells, 2 lights across, 2px padding.
    assert sheet.shape == (9 * 50 + 2, 2 * 50 + 2, 3)
    report = cli.run(cfg)
    assert report.written == 0 and "nothing to do" in capsys.readouterr().out


@pytest.mark.slow  # a fresh interpreter: ~12 s loaded (test_missing_out_dir_and_unknown_key stays fast)
def test_console_script_reports_bad_key(tmp_path):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    proc = subprocess.run(
        [sys.executable, "-m", "difareli.cli.synth", f"out_dir={tmp_path / 'x'}", "resolution=8"],
        capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120,
    )
    assert proc.returncode != 0
    assert "resolution=8 is invalid" in proc.stderr
    assert os.listdir(tmp_path) == []  # no outputs/ or .hydra/ littering the working directory


@pytest.mark.parametrize("overrides", [
    ["inputs=estimated_light"],
    ["realism=lambertian", "inputs=exact", "cam_jitter=0.1", "light_group_size=1", "effects.specular=true",
     "shading_region=mesh", "shadow_visible=0.3", "splits.train=0.5", "splits.val=0.25", "splits.test=0.25"],
])
def test_store_command_regenerates_the_store(overrides, tmp_path):
    """The command read back from a store's header makes the same store: a rerun of it finds nothing to do (the
    resume refuses a header that differs in any key), and it names only the keys that differ from the defaults."""
    from difareli.synth.command import synth_command

    out = tmp_path / "sf"
    cli.run(_cfg([f"out_dir={out}", "subjects=2", "lights=2", "resolution=16", "workers=1", "preview.enabled=false",
                  *overrides]))
    command = synth_command(out)
    words = command.split()
    assert words[:2] == ["difareli-synth", f"out_dir={out}"]
    assert sorted(words[2:8]) == sorted(["subjects=2", "lights=2", "resolution=16", "seed=0",
                                        f"realism={'lambertian' if len(overrides) > 1 else 'full'}",
                                        f"inputs={'exact' if len(overrides) > 1 else 'estimated_light'}"])
    assert sorted(words[8:]) == sorted(o for o in overrides if not o.startswith(("realism=", "inputs=")))
    report = cli.run(_cfg([*words[1:], "workers=1", "preview.enabled=false"]))
    assert report.written == 0 and report.skipped == 4
    # One key changed: the resume refuses it, so the header does decide the command.
    with pytest.raises(ConfigError):
        cli.run(_cfg([*words[1:], "cam_jitter=0.07", "workers=1", "preview.enabled=false"]))


def test_store_command_refuses_a_store_synth_did_not_make():
    from difareli.synth.command import synth_command

    with pytest.raises(ValueError, match="difareli-multipie|state its command"):
        synth_command("data/mp", {"generator": "multipie"})


@pytest.mark.parametrize("subjects,warned", [(2, True), (4, True), (6, False)])
def test_a_store_too_small_for_a_test_split_is_said(monkeypatch, tmp_path, subjects, warned):
    """Before (issue 64, our probe): difareli-synth subjects=2 lights=2 wrote a store whose splits put every subject
    in train, without a word; difareli-benchmark then found no pairs on it."""
    import warnings

    from difareli.synth import generator

    def stop(*a, **k):
        raise RuntimeError("stop before rendering")

    monkeypatch.setattr(generator, "_open_store", stop)
    with warnings.catch_warnings(record=True) as caught, pytest.raises(RuntimeError, match="stop before rendering"):
        warnings.simplefilter("always")
        generator.generate(str(tmp_path / "s"), subjects=subjects, lights=2, resolution=32, seed=0, inputs="exact")
    said = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    want = (f"subjects={subjects} make {subjects // 2} light group(s) of 2, too few for a test split (3 or more): the "
            "store has no evaluation pairs, so difareli-benchmark cannot score on it; give subjects=8 or more for one")
    assert said == ([want] if warned else []), said
