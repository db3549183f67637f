"""Processes that behave on a shared machine: workers that die with their parent, threads that sleep
when idle.

Use :func:`die_with_parent` as a ``ProcessPoolExecutor`` initializer with the parent's pid. On Linux the
kernel delivers SIGKILL to the worker the moment its parent exits, however it exits (SIGKILL included,
``prctl(PR_SET_PDEATHSIG)``); elsewhere a daemon thread polls the parent pid and exits the worker.

:func:`openmp_for_machine` chooses how torch's idle OpenMP threads (libgomp) wait, before torch loads. Left to
itself libgomp spins 300,000 iterations after every parallel region before a thread sleeps: alone on a machine that
is what keeps a small network fast (with passive waiting every operator pays a thread wake-up: a 64-px relight at
batch 1 took 2.1x as long and ``difareli-train`` 1.22x, docs/perf/README.md); beside another job those spinning
threads hold the cores the other job needs (the same relight took 1.75 s to 50 s between rounds on a shared machine).
So a command waits passively (``OMP_WAIT_POLICY=PASSIVE``) only where other work is running when it starts
(:func:`machine_busy`), and an explicit setting in the environment always wins. libgomp reads the variable once,
when torch loads it, so this must run before ``import torch`` (a console entry's first line); processes started
later inherit it either way.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time

_PR_SET_PDEATHSIG = 1
#: OpenMP settings a command starts with on a busy machine unless its environment sets them (the module docstring).
OPENMP_DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE"}
#: The machine counts as busy when other runnable threads fill at least this share of the CPUs this process may use,
#: and are at least BUSY_MIN (a quiet machine shows one now and then: the shell or agent that started the command).
BUSY_SHARE, BUSY_MIN = 0.5, 2
_SET_BEFORE_TORCH: dict[str, str] = {}


def runnable_elsewhere(samples: int = 7, interval: float = 0.01, stat: str = "/proc/stat") -> float | None:
    """How many threads other than this one are runnable right now: the median of ``samples`` readings of
    ``procs_running`` in /proc/stat (which counts the reader too), ``interval`` seconds apart; None where the
    file cannot be read. A snapshot, not the load average: the load a finished command leaves behind decays over
    minutes and would make the next command of a script wait passively on a quiet machine."""
    counts = []
    for i in range(samples):
        running = _procs_running(stat)
        if running is None:
            return None
        counts.append(running - 1)
        if i + 1 < samples:
            time.sleep(interval)
    return float(sorted(counts)[len(counts) // 2])


def _procs_running(stat: str) -> int | None:
    """``procs_running`` of a /proc/stat file; None where it cannot be read or has no such line."""
    try:
        with open(stat) as f:
            line = next((ln for ln in f if ln.startswith("procs_running")), None)
    except OSError:
        return None
    return None if line is None else int(line.split()[1])


def machine_busy(others: float | None = None, cpus: int | None = None) -> bool:
    """Whether other work holds at least :data:`BUSY_SHARE` of the CPUs this process may run on and
    :data:`BUSY_MIN` threads (``others``: :func:`runnable_elsewhere` by default; False where it cannot be told)."""
    others = runnable_elsewhere() if others is None else others
    if others is None:
        return False
    if cpus is None:
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return others >= max(BUSY_MIN, BUSY_SHARE * cpus)


def openmp_for_machine(environ: dict[str, str] | None = None, busy: bool | None = None) -> bool:
    """On a busy machine (``busy``, default :func:`machine_busy`) set :data:`OPENMP_DEFAULTS` where ``environ``
    (default ``os.environ``) leaves them unset, so idle threads sleep at once; on a quiet one leave libgomp's own
    policy. True if it set them and this process's OpenMP runtime will see them (torch not imported yet)."""
    env = os.environ if environ is None else environ
    if all(key in env for key in OPENMP_DEFAULTS) or not (machine_busy() if busy is None else busy):
        return False
    for key, value in OPENMP_DEFAULTS.items():
        env.setdefault(key, value)
    effective = "torch" not in sys.modules
    if effective and environ is None:
        _SET_BEFORE_TORCH.update({k: env[k] for k in OPENMP_DEFAULTS})
    return effective


def openmp_wait_policy() -> str:
    """The wait policy this process's OpenMP runtime uses, as far as Python can tell: what :func:`openmp_for_machine`
    set before torch loaded, else what the process was started with, else libgomp's default (spin, then sleep)."""
    if "OMP_WAIT_POLICY" in _SET_BEFORE_TORCH:
        return _SET_BEFORE_TORCH["OMP_WAIT_POLICY"]
    try:  # the environment the process started with (os.environ changes after exec are not in it)
        with open("/proc/self/environ", "rb") as f:
            start = dict(kv.split(b"=", 1) for kv in f.read().split(b"\0") if b"=" in kv)
        value = start.get(b"OMP_WAIT_POLICY")
    except OSError:
        value = os.environ.get("OMP_WAIT_POLICY", "").encode() or None
    return value.decode().upper() if value else "unset (libgomp spins 300k iterations, then sleeps)"


def _set_pdeathsig() -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent_pid: int, interval: float) -> None:
    while True:
        # Re-parented (to init or a subreaper) once the parent is gone.
        if os.getppid() != parent_pid:
            os._exit(1)
        time.sleep(interval)


def die_with_parent(parent_pid: int, interval: float = 0.5) -> None:
    """Make this (worker) process exit when ``parent_pid`` dies; call it first thing in the worker."""
    # The parent may have died between fork and now, before the kernel knew to signal us.
    if os.getppid() != parent_pid:
        os._exit(1)
    _set_pdeathsig()
    # Also a watchdog thread: covers non-Linux systems and a pdeathsig lost to a dying thread of the parent.
    threading.Thread(target=_watch, args=(parent_pid, interval), daemon=True, name="die-with-parent").start()
