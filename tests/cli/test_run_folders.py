"""Run folders cannot collide: two commands started in the same second get different run and multirun
folders, and one run sees one folder name however often its config is read."""

from __future__ import annotations

import multiprocessing as mp
import re
from datetime import datetime
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.utils import setup_globals

from difareli import configs


class _Frozen(datetime):
    """Every clock read in the same second: what two commands started together see."""

    @classmethod
    def now(cls, tz=None):
        return cls(2026, 12, 4, 20, 15, 3)


def _folders(log_dir: str) -> tuple[str, str]:
    setup_globals()  # Hydra's own resolvers, as under @hydra.main
    with initialize_config_dir(str(configs.CONFIG_DIR), version_base="1.3"):
        cfg = compose("train", overrides=[f"paths.log_dir={log_dir}"], return_hydra_config=True)
    run, sweep = cfg.hydra.run.dir, cfg.hydra.sweep.dir
    assert cfg.hydra.run.dir == run  # read again: the cached name, not a new draw
    return run, sweep


def _child(log_dir: str, conn) -> None:
    conn.send(_folders(log_dir))
    conn.close()


@pytest.fixture
def same_second(monkeypatch):
    monkeypatch.setattr(configs, "datetime", _Frozen, raising=False)


def test_two_processes_in_the_same_second_get_different_folders(tmp_path, same_second):
    here = _folders(str(tmp_path))
    ctx = mp.get_context("fork")  # the child inherits the frozen clock
    parent_end, child_end = ctx.Pipe()
    child = ctx.Process(target=_child, args=(str(tmp_path), child_end))
    child.start()
    there = parent_end.recv()
    child.join(60)
    assert child.exitcode == 0
    for mine, theirs, kind in zip(here, there, ("runs", "multiruns")):
        assert Path(mine).parent == Path(theirs).parent == tmp_path / "train" / kind
        assert mine != theirs
        # Both carry the same (frozen) second: only the process part tells them apart.
        assert Path(mine).name.startswith("2026-12-04_20-15-03_")
        assert Path(theirs).name.startswith("2026-12-04_20-15-03_")


def test_folder_name_is_time_pid_and_random(tmp_path, same_second):
    import os

    run, sweep = _folders(str(tmp_path))
    m = re.fullmatch(r"2026-12-04_20-15-03_(\d+)-([0-9a-f]{4})", Path(run).name)
    assert m and int(m.group(1)) == os.getpid()
    # Two compositions in one process (e.g. two trainings in one test or sweep) differ too, by the random part.
    again = {Path(_folders(str(tmp_path))[0]).name for _ in range(4)} | {Path(run).name}
    assert len(again) == 5
    assert Path(sweep).parent.name == "multiruns"
