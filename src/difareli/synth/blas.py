"""One BLAS thread while rendering: bit-identical SynthFaces records in this process and in pool workers."""

from __future__ import annotations

import contextlib
import ctypes
import re


@contextlib.contextmanager
def single_thread_blas():
    """Run numpy's OpenBLAS on one thread: its multi-threaded gemv sums in a thread-count dependent order,
    which changed mesh vertices in the last float bit (and pixels at silhouettes) between a run in this
    process and one in pool workers. (threadpoolctl does this too but is not a dependency.)"""
    libs = []
    try:
        with open("/proc/self/maps") as f:
            maps = f.read()
    except OSError:
        maps = ""
    for path in sorted(set(re.findall(r"(/\S*openblas\S*\.so\S*)", maps))):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix, suffix in (("scipy_openblas", "64_"), ("openblas", "64_"), ("openblas", ""),
                               ("scipy_openblas", "")):
            get, set_ = f"{prefix}_get_num_threads{suffix}", f"{prefix}_set_num_threads{suffix}"
            if hasattr(lib, get) and hasattr(lib, set_):
                libs.append((getattr(lib, set_), int(getattr(lib, get)())))
                break
    for set_, _ in libs:
        set_(ctypes.c_int(1))
    try:
        yield
    finally:
        for set_, n in libs:
            set_(ctypes.c_int(n))
