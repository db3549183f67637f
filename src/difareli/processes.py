"""Worker processes that die with their parent (issue 15): a killed CLI must not leave orphans behind.

Use :func:`die_with_parent` as a ``ProcessPoolExecutor`` initializer with the parent's pid. On Linux the
kernel delivers SIGKILL to the worker the moment its parent exits, however it exits (SIGKILL included,
``prctl(PR_SET_PDEATHSIG)``); elsewhere a daemon thread polls the parent pid and exits the worker.
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
