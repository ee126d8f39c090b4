"""Exception types of heliocal.

Every message is one line that says what is wrong and how to fix it; the CLI prints it as
``Error: <message>`` on stderr and exits with code 1. Library code raises these instead of
printing.
"""

from __future__ import annotations

import errno as _errno
import re

__all__ = [
    "HeliocalError",
    "InputError",
    "StageInputError",
    "SchemaError",
    "ParameterError",
    "FitError",
    "WorkdirBusyError",
    "UnsafePathError",
    "ClusterError",
    "check_choice",
    "check_int",
    "check_float",
    "resource_error_message",
]


class HeliocalError(Exception):
    """Base class: an error the user can act on (message is one line)."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


class InputError(HeliocalError):
    """A source file cannot be read at all (missing, empty, wrong format, required columns absent)."""


class StageInputError(HeliocalError):
    """A stage's input artifact is missing or stale: the message names the stage to run first."""


class SchemaError(HeliocalError):
    """An artifact does not match its declared schema or was written by an incompatible version."""


class ParameterError(HeliocalError, ValueError):
    """An option has a value outside its allowed set (scikit-learn's wording)."""


class FitError(HeliocalError):
    """A fit could not be carried out (for example no heliostat has enough measurements)."""


class WorkdirBusyError(HeliocalError):
    """Another stage is writing the work directory (see :mod:`heliocal.pipeline.artifacts.workdir_lock`):
    the message names it (stage, pid, host, start time) and what to do."""


class UnsafePathError(InputError, ValueError):
    """A name taken from the data cannot be used as a file name inside its folder (see
    :func:`heliocal.pipeline.artifacts.store.safe_child`)."""


class ClusterError(HeliocalError):
    """A Dask scheduler cannot be reached at the address given, or the connection to it was lost
    while its tasks ran (see :mod:`heliocal.pipeline.runtime.parallel`)."""


def _param_error(name: str, func: str, must: str, value) -> ParameterError:
    return ParameterError(f"The '{name}' parameter of {func} must be {must}. Got {value!r} instead.")


def check_choice(value, name: str, func: str, choices) -> str:
    """Return ``value`` if it is one of ``choices``, else raise :class:`ParameterError`."""
    if value not in choices:
        options = ", ".join(repr(c) for c in choices)
        raise _param_error(name, func, f"one of {{{options}}}", value)
    return value


def check_int(value, name: str, func: str, low: int | None = None, high: int | None = None) -> int:
    """Return ``value`` as int if it is an integer in [low, high], else raise :class:`ParameterError`."""
    lo = "-inf" if low is None else str(low)
    hi = "inf" if high is None else str(high)
    interval = f"[{lo}, {hi}{']' if high is not None else ')'}"
    if isinstance(value, bool) or not float(value).is_integer() if _is_number(value) else True:
        raise _param_error(name, func, f"an int in {interval}", value)
    value = int(value)
    if (low is not None and value < low) or (high is not None and value > high):
        raise _param_error(name, func, f"an int in {interval}", value)
    return value


def check_float(value, name: str, func: str, low: float | None = None, high: float | None = None,
                low_inclusive: bool = True) -> float:
    """Return ``value`` as float if it is a finite number in the interval, else raise."""
    lo = "-inf" if low is None else f"{low:g}"
    hi = "inf" if high is None else f"{high:g}"
    interval = f"{'[' if low_inclusive else '('}{lo}, {hi}{']' if high is not None else ')'}"
    if not _is_number(value) or value != value or value in (float("inf"), float("-inf")):
        raise _param_error(name, func, f"a float in {interval}", value)
    value = float(value)
    if low is not None and (value < low or (not low_inclusive and value == low)):
        raise _param_error(name, func, f"a float in {interval}", value)
    if high is not None and value > high:
        raise _param_error(name, func, f"a float in {interval}", value)
    return value


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) or (
        hasattr(value, "dtype") and getattr(value.dtype, "kind", "") in "iuf")


#: Operating-system errors that are the user's to fix (the machine's resources or permissions),
#: with what they mean and what to do.
_RESOURCE_ERRNOS = {
    _errno.ENOSPC: ("no space left on the device",
                    "free space on that disk or use another --workdir"),
    _errno.EDQUOT: ("disk quota exceeded", "free space on that disk or use another --workdir"),
    _errno.EFBIG: ("file too large for the file system", "use another --workdir"),
    _errno.EROFS: ("the file system is read-only", "use a writable --workdir"),
    _errno.EACCES: ("permission denied", "make it writable (and readable) for this user or use "
                                         "another --workdir"),
    _errno.EPERM: ("operation not permitted", "make it writable for this user or use another "
                                              "--workdir"),
    _errno.EMFILE: ("too many open files", "raise the limit (ulimit -n) or use fewer --workers"),
    _errno.ENFILE: ("too many open files in the system", "close other programs or use fewer "
                                                         "--workers"),
}


def resource_error_message(exc: BaseException) -> str | None:
    """A one-line message for an :class:`OSError` that is the user's to fix (full disk, read-only
    or forbidden work directory, too many open files), ``None`` for any other exception.

    pyarrow reports such errors as ``OSError`` without ``errno`` but with ``[errno N]`` in the
    text; both forms are recognised.
    """
    if not isinstance(exc, OSError):
        return None
    code = exc.errno
    if code is None:
        m = re.search(r"\[?errno[ :]*(\d+)", str(exc), re.IGNORECASE)
        code = int(m.group(1)) if m else None
    if code not in _RESOURCE_ERRNOS:
        return None
    what, fix = _RESOURCE_ERRNOS[code]
    where = exc.filename if getattr(exc, "filename", None) else None
    name = _errno.errorcode.get(code, str(code))
    place = f"{where}: " if where else ""
    return (f"{place}{what} ({name}); {fix}, then rerun the command. This is not a bug in heliocal: "
            "nothing was committed, the stage's previous outputs are still the ones in use")
