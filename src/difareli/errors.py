"""User errors: one style for every console script, and the input checks that raise them.

A *user error* (bad config value, unreadable or corrupt file, non-finite input) ends a CLI with one or two
lines ``difareli-<name>: <input>: <what is wrong>; <the fix>`` on stderr and exit status 2, no traceback.
Anything else is an internal error and keeps its traceback. ``DIFARELI_DEBUG=1`` (or ``HYDRA_FULL_ERROR=1``)
re-raises user errors too, with the traceback.

What counts as a user error (:func:`user_message`) is decided by the exception's type:

- :class:`UserError` and its subclasses: every message difareli writes for a user. The subclasses keep the
  builtin types callers catch: :class:`MissingError` is a ``KeyError`` (not found, missing encoding, unknown
  key), :class:`UserFileNotFoundError` a ``FileNotFoundError``; project types such as
  ``inputs.MissingEncodingError`` and ``synth.config.ConfigError`` derive from them. A plain ``ValueError`` /
  ``KeyError`` / ``FileNotFoundError`` is not one, wherever it was raised: a bug or an unchecked input, so it
  keeps the traceback;
- ``OSError`` naming a file with errno ENOENT/EACCES/EPERM/EROFS/ENOSPC/EISDIR/ENOTDIR/EEXIST (the
  environment, not the code);
- OmegaConf's missing-mandatory-value and unknown-key errors (a config the user composed).

Hydra's ``InstantiationException`` is unwrapped to the exception that caused it.
"""

from __future__ import annotations

import errno
import functools
import json
import math
import os
import re
import signal
import sys
import threading
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

#: Exit status of a user error (like argparse's usage errors).
EXIT_USER = 2
#: SH light coefficients beyond this are not a light a face can be lit with (DECA lights stay within ~10).
LIGHT_MAX_ABS = 1e4
#: A *target* light's bound: SynthFaces and fitted photo lights stay below ~5 (irradiance ~1-2 on a face whose
#: pixels are albedo x irradiance in [0, 1]); a light 20x brighter than that relights to saturated noise.
TARGET_LIGHT_MAX_ABS = 100.0
#: numpy's ``ndarray.tofile`` (what ``np.save`` writes an array's data with) reports a short write, the way a full
#: disk shows mid-array, as a bare ``OSError("<n> requested and <m> written")``: the errno is lost.
_SHORT_WRITE = re.compile(r"\d+ requested and \d+ written")
_USER_ERRNOS = {errno.ENOENT, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EISDIR, errno.ENOTDIR,
                errno.EEXIST}


class UserError(ValueError):
    """A bad input: the message names the input, what is wrong and the fix (one or two lines).

    A ValueError, so code that already catches validation ValueErrors keeps working."""

    def __str__(self) -> str:  # the message itself (a KeyError subclass would quote it)
        return str(self.args[0]) if len(self.args) == 1 else super().__str__()


class MissingError(UserError, KeyError):
    """Something asked for is not there (a record, an encoding, a key, a name): a KeyError to its catchers."""


class UserFileNotFoundError(UserError, FileNotFoundError):
    """An input file or folder that does not exist: a FileNotFoundError to its catchers. Raised with one
    message argument (its ``errno`` and ``filename`` stay None: the message names the path)."""


class NonFiniteError(UserError):
    """An array that must be finite holds NaN or Inf (or absurd magnitudes)."""


# ---------------------------------------------------------------------------------------------- classifying
def is_no_space(exc: BaseException) -> bool:
    """Whether ``exc`` is a full disk or an exceeded quota (ENOSPC, EDQUOT, or numpy's short write)."""
    if not isinstance(exc, OSError):
        return False
    return exc.errno in (errno.ENOSPC, errno.EDQUOT) or (exc.errno is None and bool(_SHORT_WRITE.fullmatch(str(exc))))


def os_reason(exc: OSError) -> str:
    """What went wrong, for a message: the OS's words, or numpy's short write named as one."""
    return exc.strerror or (f"short write: {exc}" if _SHORT_WRITE.fullmatch(str(exc)) else str(exc))


def user_message(exc: BaseException) -> str | None:
    """The one/two-line message if ``exc`` is a user error (see the module docstring), else None."""
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, MissingMandatoryValue

    try:
        from hydra.errors import InstantiationException
    except ImportError:  # pragma: no cover - hydra is a dependency
        InstantiationException = ()  # type: ignore[assignment]
    while isinstance(exc, InstantiationException) and exc.__cause__ is not None:
        exc = exc.__cause__
    if isinstance(exc, UserError):
        return str(exc)
    if isinstance(exc, MissingMandatoryValue):
        key = getattr(exc, "full_key", None) or "a value"
        return f"{key} is required (it is ??? in the config); give it on the command line: {key}=..."
    if isinstance(exc, (ConfigKeyError, ConfigAttributeError)):
        return f"{str(exc).splitlines()[0]}; check the spelling against the config (--cfg job prints it)"
    if is_no_space(exc):
        where = f" writing {exc.filename}" if exc.filename else ""
        return (f"no space left on the device{where} ({os_reason(exc)}); free space or give another output folder "
                "(files and records already complete are kept)")
    if isinstance(exc, OSError) and exc.errno in _USER_ERRNOS and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror}; check the path and its permissions"
    return None


def _debug() -> bool:
    return os.environ.get("DIFARELI_DEBUG", "") not in ("", "0") or os.environ.get("HYDRA_FULL_ERROR") == "1"


class Terminated(KeyboardInterrupt):
    """SIGTERM, turned into an exception so ``finally`` blocks and atomic writers clean up."""


def _on_sigterm(signum, frame):
    raise Terminated()


def cli_entry(name: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorate a console script's task function (inside ``@hydra.main``, which would print a traceback):
    user errors -> ``difareli-<name>: <message>`` and exit 2; SIGTERM/SIGINT -> a clean stop (exit 143/130)."""
    prog = f"difareli-{name}"

    def wrap(fn):
        @functools.wraps(fn)
        def task(*args, **kwargs):
            # A warning is one line named by the command, like its errors (not Python's file:line and source).
            warnings.formatwarning = lambda message, category, *_, **__: f"{prog}: warning: {message}\n"
            if threading_main():
                signal.signal(signal.SIGTERM, _on_sigterm)
            try:
                return fn(*args, **kwargs)
            except KeyboardInterrupt as e:
                how = "SIGTERM" if isinstance(e, Terminated) else "interrupted"
                print(f"{prog}: stopped ({how}); records already written are complete, rerun to resume",
                      file=sys.stderr)
                sys.exit(143 if isinstance(e, Terminated) else 130)
            except Exception as e:
                msg = user_message(e)
                if msg is None or _debug():
                    raise
                print(f"{prog}: {msg}", file=sys.stderr)
                if in_multirun():  # the other jobs still run; the sweep's summary reports this one and exits 2
                    record_failure(msg)
                    return None
                sys.exit(EXIT_USER)

        return task

    return wrap


#: Where a multirun's failed jobs are recorded (``<sweep dir>/failed_jobs.jsonl``; difareli.cli.sweep reports them).
FAILED_JOBS = "failed_jobs.jsonl"


def in_multirun() -> bool:
    """Whether the current task runs as one job of a Hydra multirun."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    except Exception:  # noqa: BLE001 - outside Hydra
        return False


def record_failure(message: str) -> None:
    """Append this job's failure (number, overrides, message) to the sweep's ``failed_jobs.jsonl``."""
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    line = json.dumps({"job": hc.job.get("num"), "overrides": list(hc.overrides.task), "message": message})
    path = Path(hc.sweep.dir) / FAILED_JOBS
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:  # one short line per write: appends from concurrent jobs do not interleave
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())


def threading_main() -> bool:
    """Signal handlers can only be installed from the main thread."""
    return threading.current_thread() is threading.main_thread()


# ------------------------------------------------------------------------------------------ config values
def check_int(value: Any, key: str, minimum: int = 1, *, allow_none: bool = False,
              maximum: int | None = None) -> int | None:
    """``value`` as an int >= ``minimum`` (and <= ``maximum`` where given; ``None`` allowed if ``allow_none``);
    bools and 2.7 are errors."""
    if value is None and allow_none:
        return None
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    if not ok or value < minimum or (maximum is not None and value > maximum):
        none = " or null" if allow_none else ""
        bound = f">= {minimum}" if maximum is None else f"from {minimum} to {maximum}"
        raise UserError(f"{key}={value!r} is invalid: must be an integer {bound}{none}; "
                        f"e.g. {key}={max(minimum, 1)}")
    return int(value)


def check_bool(value: Any, key: str) -> bool:
    """A true/false setting as YAML gives it (``true`` / ``false``), else a UserError naming the key: ``strict=no``
    or ``strict=1`` is no boolean, not a truthy string."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise UserError(f"{key}={value!r} is invalid: give {key}=true or {key}=false")


def check_choice(value: Any, key: str, choices: Sequence[Any]) -> Any:
    """``value`` if it is one of ``choices``, else a one-line UserError naming the ``key`` and them."""
    if value not in choices:
        raise UserError(f"{key}={value!r}: use one of {', '.join(map(str, choices))}")
    return value


def check_number(value: Any, key: str, *, allow_none: bool = True, limit: float = 1e6) -> float | None:
    """``value`` as a finite float with ``|value| <= limit`` (``None`` allowed if ``allow_none``); a number
    that is not finite or too large is a NonFiniteError (a bad value, like a NaN in an array)."""
    if value is None and allow_none:
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise UserError(f"{key}={value!r} is invalid: must be a number") from None
    if not math.isfinite(x) or abs(x) > limit:
        raise NonFiniteError(f"{key}={value!r} is invalid: must be a finite number with magnitude <= {limit:g}")
    return x


def check_out_dir(path: Any, key: str = "out_dir") -> Path:
    """An output folder that is (or can be created as) a writable directory; checked before any work."""
    if path is None or str(path) == "":
        raise UserError(f"{key} is empty: give an output folder, {key}=<dir>")
    p = Path(str(path))
    probe = p
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        what = "is a file" if probe == p else f"is below {probe}, which is a file"
        raise UserError(f"{key}={p} {what}, not a folder; give a folder path, {key}=<dir>")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise UserError(f"{key}={p}: {probe} is not writable; choose a writable folder or fix its permissions")
    return p


def check_file(path: Any, key: str) -> Path:
    """An input file that exists and is readable (a missing one is a UserFileNotFoundError: a FileNotFoundError, as
    callers expect)."""
    p = Path(str(path))
    if not p.is_file():
        what = "is a folder" if p.is_dir() else "does not exist"
        raise UserFileNotFoundError(f"{key}={p} {what}; give the path of an existing file")
    if not os.access(p, os.R_OK):
        raise UserError(f"{key}={p} is not readable; fix its permissions")
    return p


# ------------------------------------------------------------------------------------------ array values
def check_finite(array: Any, what: str, *, max_abs: float | None = None, fix: str = "") -> np.ndarray:
    """``array`` as a numpy array if every value is finite (and ``|x| <= max_abs``), else NonFiniteError."""
    a = np.asarray(array)
    if a.dtype.kind not in "fc":
        if a.dtype.kind not in "biu":
            raise NonFiniteError(f"{what}: values of type {a.dtype} are not numbers{'; ' + fix if fix else ''}")
        return a
    bad = ~np.isfinite(a)
    tail = f"; {fix}" if fix else ""
    if bad.any():
        first = np.unravel_index(int(np.argmax(bad)), a.shape) if a.ndim else ()
        raise NonFiniteError(f"{what}: {int(bad.sum())} of {a.size} values are NaN or Inf "
                             f"(first at index {tuple(int(i) for i in first)}){tail}")
    if max_abs is not None and a.size and float(np.abs(a).max()) > max_abs:
        raise NonFiniteError(f"{what}: magnitude {float(np.abs(a).max()):.3g} exceeds {max_abs:g}, not a "
                             f"plausible value{tail}")
    return a


def check_light(light: Any, what: str, max_abs: float = LIGHT_MAX_ABS) -> np.ndarray:
    """A finite 9x3 SH light of plausible magnitude (``|l| <= max_abs``), as float64."""
    a = check_finite(np.asarray(light, dtype=np.float64) if np.asarray(light).dtype.kind in "biuf" else light,
                     what, max_abs=max_abs, fix="give a 9x3 SH light in DECA's basis (difareli.lighting.sh)")
    return a.astype(np.float64)


def check_record(arrays: Mapping[str, Any], record_id: str, store_root: Any) -> Mapping[str, Any]:
    """Every float encoding of a record read for relighting or training is finite; the error names the
    record, the encoding and the store."""
    for name, arr in arrays.items():
        check_finite(arr, f"record {record_id!r}, encoding {name!r} in store {store_root}",
                     fix=f"regenerate or remove the record (difareli-store verify {store_root} lists all)")
    return arrays


def check_output(image: Any, what: str) -> np.ndarray:
    """A result image before it is written or scored: finite floats, or a uint8 HxWx3 image."""
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[-1] != 3:
        raise NonFiniteError(f"{what}: result has shape {a.shape}, expected HxWx3")
    return check_finite(a, what, fix="the model or its inputs produced invalid values")
