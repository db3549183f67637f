"""difareli-train ends with one line: steps done of planned, why it stopped, the checkpoint, the next command."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest

from difareli.cli.train import train
from tests.helpers import compose_train, tiny_cpu_overrides

pytestmark = pytest.mark.usefixtures("one_thread")


def _base(store: Path) -> list[str]:
    return [*tiny_cpu_overrides(store), "model=difareli", "trainer.limit_val_batches=1", "logger=[]"]


def _last_line(capsys) -> str:
    return capsys.readouterr().out.strip().splitlines()[-1]


@pytest.mark.slow  # a training run: the default run has to finish in minutes at load 4
def test_a_finished_run_names_its_steps_checkpoint_and_the_relight_command(synth_store, tmp_path, capsys):
    cfg = compose_train(tmp_path / "run", [*_base(synth_store), "trainer.max_steps=2",
                                           "trainer.val_check_interval=2"])
    out = train(cfg)
    line = _last_line(capsys)
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    assert out["trainer"].global_step == 2 and ckpt.is_file()
    assert line.startswith("train: 2 of 2 steps, stopped by max_steps=2; ")
    assert f"checkpoint {ckpt};" in line
    assert line.endswith(f"next: relight: difareli-relight checkpoint={ckpt} store={synth_store} target.yaw=45")


@pytest.mark.slow  # two training runs, the first cut by its time limit
def test_a_run_cut_by_max_time_says_so_and_its_resume_command_goes_on(synth_store, tmp_path, capsys):
    # A zero time limit stops the run whatever the machine's speed: the line must not call it done.
    first = compose_train(tmp_path / "a", [*_base(synth_store), "trainer.max_steps=1", "trainer.val_check_interval=1"])
    train(first)
    ckpt = Path(first.paths.output_dir) / "checkpoints" / "last.ckpt"
    given = [*_base(synth_store), "trainer.max_steps=3", "trainer.val_check_interval=1",
             "trainer.max_time=00:00:00:00", f"ckpt_path={ckpt}"]
    assert train(compose_train(tmp_path / "b", given))["trainer"].global_step == 1
    line = _last_line(capsys)
    assert line.startswith(f"train: 1 of 3 steps, stopped by max_time=0:00:00; checkpoint {ckpt}; next: resume: ")
    cmd = shlex.split(line.split("next: resume: ", 1)[1])
    assert cmd[0] == "difareli-train" and cmd[-2:] == [f"ckpt_path={ckpt}", "trainer.max_time=null"]
    assert cmd[1:-2] == [o for o in given if not o.startswith(("ckpt_path=", "trainer.max_time="))]
    # The printed command continues to the planned step; under the old limit the Timer restored from the
    # checkpoint would stop it again at once.
    third = train(compose_train(tmp_path / "c", cmd[1:]))
    assert third["trainer"].global_step == 3
    assert _last_line(capsys).startswith("train: 3 of 3 steps, stopped by max_steps=3; ")


def test_a_run_stopped_before_its_first_checkpoint_says_to_rerun_with_more_time(synth_store, tmp_path, capsys):
    cfg = compose_train(tmp_path / "a", [*_base(synth_store), "trainer.max_steps=3", "trainer.val_check_interval=1",
                                         "trainer.max_time=00:00:00:00"])
    assert train(cfg)["trainer"].global_step == 0
    assert _last_line(capsys) == ("train: 0 of 3 steps, stopped by max_time=0:00:00; checkpoint none; next: rerun "
                                  "with a longer trainer.max_time (stopped before its first checkpoint)")
