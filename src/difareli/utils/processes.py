"""Processes that behave on a shared machine: workers that die with their parent, threads that sleep
when idle.

Use :func:`die_with_parent` as a ``ProcessPoolExecutor`` initializer with the parent's pid. On Linux the
kernel delivers SIGKILL to the worker the moment its parent exits, however it exits (SIGKILL included,
``prctl(PR_SET_PDEATHSIG)``); elsewhere a daemon thread polls the parent pid and exits the worker.

:func:`passive_openmp` sets ``OMP_WAIT_POLICY=PASSIVE`` where the environment leaves it unset. torch's OpenMP
runtime (libgomp) otherwise spins 300,000 iterations after every parallel region before sleeping: on a machine
shared with another job those spinning threads hold cores the other job needs, and the same relight took 1.75 s
to 50 s between rounds; passive waiting removed the spread. libgomp reads the variable once, when
torch loads it, so this must run before ``import torch`` (a console entry's first line); processes started later
inherit it either way.
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
#: OpenMP settings a command starts with unless its environment sets them (see the module docstring).
OPENMP_DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE"}
_SET_BEFORE_TORCH: dict[str, str] = {}


def passive_openmp(environ: dict[str, str] | None = None) -> bool:
    """Set :data:`OPENMP_DEFAULTS` where ``environ`` (default ``os.environ``) leaves them unset; True if this
    process's OpenMP runtime will see them (torch not imported yet). Explicit settings are kept."""
    env = os.environ if environ is None else environ
    for key, value in OPENMP_DEFAULTS.items():
        env.setdefault(key, value)
    effective = "torch" not in sys.modules
    if effective and environ is None:
        _SET_BEFORE_TORCH.update({k: env[k] for k in OPENMP_DEFAULTS})
    return effective


def openmp_wait_policy() -> str:
    """The wait policy this process's OpenMP runtime uses, as far as Python can tell: what :func:`passive_openmp`
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
