"""Exception types of heliocal.

Every message is one line that says what is wrong and how to fix it; the CLI prints it as
``Error: <message>`` on stderr and exits with code 1. Library code raises these instead of
printing.
"""

from __future__ import annotations

__all__ = [
    "HeliocalError",
    "InputError",
    "StageInputError",
    "SchemaError",
    "ParameterError",
    "FitError",
    "WorkdirBusyError",
    "UnsafePathError",
    "check_choice",
    "check_int",
    "check_float",
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
    """Another stage is writing the work directory (see :mod:`heliocal.pipeline.workdir_lock`):
    the message names it (stage, pid, host, start time) and what to do."""


class UnsafePathError(HeliocalError, ValueError):
    """A name taken from the data cannot be used as a file name inside its folder (see
    :func:`heliocal.pipeline.artifacts.safe_child`)."""


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
