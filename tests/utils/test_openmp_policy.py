"""How a command's idle OpenMP threads wait: passive on a busy machine, libgomp's own policy on a quiet one, an
explicit environment always kept (difareli.utils.processes.openmp_for_machine)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from difareli.utils import processes
from difareli.utils.processes import machine_busy, openmp_for_machine, runnable_elsewhere


def test_runnable_elsewhere_is_the_median_reading_less_the_reader(tmp_path, monkeypatch):
    stat = tmp_path / "stat"
    stat.write_text("cpu  1 2 3 4\nctxt 10\nprocs_running 3\nprocs_blocked 0\n")
    assert runnable_elsewhere(samples=1, stat=str(stat)) == 2.0  # the file's 3 less the reader
    readings = iter([1, 9, 3, 3, 2])
    monkeypatch.setattr(processes, "_procs_running", lambda path: next(readings))
    # readings 0, 8, 2, 2, 1 others: the median 2 (a burst of one reading does not decide)
    assert runnable_elsewhere(samples=5, interval=0.0, stat="S") == 2.0
    monkeypatch.undo()
    assert runnable_elsewhere(samples=1, stat=str(tmp_path / "missing")) is None
    (tmp_path / "nokey").write_text("cpu 1 2 3\n")
    assert runnable_elsewhere(samples=1, stat=str(tmp_path / "nokey")) is None


@pytest.mark.parametrize("others,cpus,busy", [
    (0, 2, False), (1, 2, False),    # a quiet 2-core machine shows one runnable thread now and then
    (2, 2, True), (3, 2, True),      # a 2-thread job beside this one
    (2, 64, False), (31, 64, False), (32, 64, True),  # half of a large machine's CPUs
    (None, 2, False),                # cannot be told: not busy
])
def test_machine_busy_threshold(others, cpus, busy, monkeypatch):
    if others is None:
        monkeypatch.setattr(processes, "runnable_elsewhere", lambda: None)
    assert machine_busy(others, cpus) is busy


def test_policy_set_only_on_a_busy_machine_and_never_over_the_environment():
    quiet, busy, given = {}, {}, {"OMP_WAIT_POLICY": "ACTIVE"}
    openmp_for_machine(quiet, busy=False)
    openmp_for_machine(busy, busy=True)
    openmp_for_machine(given, busy=True)
    assert quiet == {} and busy == {"OMP_WAIT_POLICY": "PASSIVE"} and given == {"OMP_WAIT_POLICY": "ACTIVE"}


def _libgomp_read(env: dict[str, str]) -> str:
    """What libgomp read when torch loaded it in a fresh process that first imports the console entries."""
    env = {**env, "OMP_DISPLAY_ENV": "VERBOSE"}
    out = subprocess.run([sys.executable, "-c", "import difareli.cli, torch; torch.ones(8).sum()"], env=env,
                         capture_output=True, text=True, check=True)
    if "GOMP_SPINCOUNT" not in out.stderr:
        pytest.skip("torch's OpenMP runtime here is not libgomp (nothing to read back)")
    return out.stderr


def test_console_entry_keeps_an_explicit_policy():
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    assert "OMP_WAIT_POLICY = 'ACTIVE'" in _libgomp_read({**base, "OMP_WAIT_POLICY": "ACTIVE"})
    assert "GOMP_SPINCOUNT = '0'" in _libgomp_read({**base, "OMP_WAIT_POLICY": "PASSIVE"})
    assert "GOMP_SPINCOUNT = '0'" not in _libgomp_read({**base, "OMP_WAIT_POLICY": "ACTIVE"})
