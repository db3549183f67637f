"""Silence the photo estimators' third-party noise, and only it.

- ``pkg_resources is deprecated``: a UserWarning ``face_recognition_models`` raises on import (it imports
  ``pkg_resources``); filtered by its message at import of this module.
- mediapipe's native logs: TFLite's ``INFO: Created TensorFlow Lite XNNPACK delegate``, absl's ``WARNING: All log
  messages before absl::InitializeLog() ...`` and its ``W0000``/``I0000`` lines (``inference_feedback_manager``,
  ``landmark_projection_calculator``) are written by C++ straight to file descriptor 2, where no Python filter
  reaches and ``GLOG_minloglevel`` / ``TF_CPP_MIN_LOG_LEVEL`` do not apply (absl logging, tried). :func:`native_logs`
  sends fd 2 to a temporary file while the estimators run and writes back every line that is not one of those:
  mediapipe's errors (``E``/``F`` lines), Python warnings and tracebacks still reach the terminal, in order.

``DIFARELI_NATIVE_LOGS=1`` turns the filter off (everything through, as it comes).
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading
import warnings

warnings.filterwarnings("ignore", message=r"pkg_resources is deprecated as an API", category=Warning)

#: Lines of mediapipe / TFLite / absl that carry no information for a user of the estimators.
NOISE = re.compile(
    r"^(INFO: Created TensorFlow Lite XNNPACK delegate"
    r"|WARNING: All log messages before absl::InitializeLog\(\) is called"
    r"|[IW]\d{4} [\d:.]+\s+\d+ \S+\.(cc|h):\d+\])"
)


def is_noise(line: str) -> bool:
    return bool(NOISE.match(line))


class _Capture:
    """fd 2 redirected to one temporary file while any thread is inside :func:`native_logs` (fd 2 is the
    process's: two threads capturing each on its own would restore each other's descriptors)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.depth, self.fd, self.saved, self.tmp = 0, None, None, None

    def enter(self, fd: int) -> None:
        with self.lock:
            self.depth += 1
            if self.depth > 1:
                return
            sys.stderr.flush()
            self.fd, self.saved, self.tmp = fd, os.dup(fd), tempfile.TemporaryFile(mode="w+b")
            os.dup2(self.tmp.fileno(), fd)

    def exit(self) -> None:
        with self.lock:
            self.depth -= 1
            if self.depth > 0:
                return
            with contextlib.suppress(Exception):
                sys.stderr.flush()
            os.dup2(self.saved, self.fd)
            os.close(self.saved)
            tmp, self.tmp = self.tmp, None
        with tmp:
            tmp.seek(0)
            kept = [ln for ln in tmp.read().decode("utf-8", "replace").splitlines(keepends=True) if not is_noise(ln)]
        if kept:
            sys.stderr.write("".join(kept))
            sys.stderr.flush()


_CAPTURE = _Capture()


@contextlib.contextmanager
def native_logs():
    """Run the body with fd 2 captured; afterwards write back its lines that are not :data:`NOISE`. Nested and
    concurrent uses (the reader thread of :mod:`.stream` and the estimators) share one capture, written back
    when the last of them ends."""
    if os.environ.get("DIFARELI_NATIVE_LOGS") == "1":
        yield
        return
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # pytest's capture, a notebook: no real fd 2 to redirect
        fd = None
    if fd is None:
        yield
        return
    _CAPTURE.enter(fd)
    try:
        yield
    finally:
        _CAPTURE.exit()
