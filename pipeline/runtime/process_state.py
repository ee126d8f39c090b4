"""Process-wide settings a library call may change only for its own duration.

torch keeps its deterministic-algorithms flag and its intra-op thread count per process, and
environment variables are process-wide too. heliocal needs all three while it works (deterministic
kernels for seeded, repeatable fits; one thread for tiny networks; one-thread BLAS variables for
worker pools), but a library must not leave them changed for the program that called it.

* :func:`one_thread` / :func:`single_threaded`: torch (optionally also the BLAS pools behind numpy
  and scipy, through threadpoolctl) on one thread for the duration, then back to what it was.
* :func:`restores_process_state`: a decorator for the entry points of the library (the stages,
  ``aim_steps``): whatever the call did to torch's deterministic flag, its thread count or
  ``os.environ`` is undone when it returns or raises.
* :func:`deterministic_torch`: set torch's deterministic flag for its kernels without importing
  torch's compiler (which ``torch.use_deterministic_algorithms`` does).

torch is imported inside the functions, so importing this module stays cheap (the CLI imports
the stages lazily, but tools that only read artifacts should not pay for torch either).
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys
from typing import Callable, Iterator, TypeVar

__all__ = ["ProcessState", "one_thread", "single_threaded", "restored_process_state",
           "restores_process_state", "deterministic_torch"]

F = TypeVar("F", bound=Callable)


def deterministic_torch(mode: bool = True, *, warn_only: bool = True) -> None:
    """Set torch's deterministic-algorithms flag, as ``torch.use_deterministic_algorithms(mode,
    warn_only=warn_only)`` does for the kernels heliocal runs (eager CPU ops).

    That public function also sets the flag in the configuration of torch's compiler and so
    imports ``torch._inductor`` (and ``torch._dynamo``) on its first call: about 1.1 s of CPU in
    every process, more than heliocal's own modules take to import. heliocal never compiles, so
    this sets only the kernels' flag (``torch._C._set_deterministic_algorithms``, what the
    public function calls), and falls back to the public function on a torch without it.
    ``torch.are_deterministic_algorithms_enabled()`` reads the flag either way."""
    import torch

    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None:
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
    else:
        setter(mode, warn_only=warn_only)


@contextlib.contextmanager
def one_thread(*, blas: bool = False, torch_threads: bool = True) -> Iterator[None]:
    """Run torch on one thread (and with ``blas=True`` the BLAS pools behind numpy and scipy,
    through threadpoolctl): the networks and per-heliostat problems are tiny, and with several
    threads the per-call overhead of the intra-op pool dominates (a 177 x 2 x 2 ``bmm`` takes 2 us
    on one thread and up to milliseconds on two busy ones). Restores the previous settings.
    ``torch_threads=False`` leaves torch alone, for work that runs none (the report's figures):
    importing it only to set its threads costs about 1.3 s."""
    torch = None
    if torch_threads:
        import torch

        before = torch.get_num_threads()
        torch.set_num_threads(1)
    limits = None
    if blas:
        try:
            from threadpoolctl import threadpool_limits

            limits = threadpool_limits(1)
        except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
            pass
    try:
        yield
    finally:
        if torch is not None:
            torch.set_num_threads(before)
        if limits is not None:
            limits.restore_original_limits()


def single_threaded(func: F) -> F:
    """Decorator: ``func`` runs inside :func:`one_thread` (torch on one thread)."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with one_thread():
            return func(*args, **kwargs)
    return wrapper  # type: ignore[return-value]


class ProcessState(dict):
    """A snapshot of the settings :func:`restored_process_state` guards (comparable with ``==``):
    torch's deterministic flag and its warn-only mode, torch's thread count, and a copy of
    ``os.environ``.

    torch's settings are read only when torch is imported already (``torch`` is None otherwise):
    a call that does not use torch (``info``, ``report``) does not pay torch's import for its
    guard. A call that imports torch itself leaves it as torch starts, deterministic off; a
    thread count it changes is restored by :func:`one_thread`, which every such change uses."""

    @classmethod
    def capture(cls) -> "ProcessState":
        torch = sys.modules.get("torch")
        settings = None if torch is None else {
            "deterministic": torch.are_deterministic_algorithms_enabled(),
            "deterministic_warn_only": torch.is_deterministic_algorithms_warn_only_enabled(),
            "threads": torch.get_num_threads()}
        return cls(torch=settings, environ=dict(os.environ))

    def restore(self) -> None:
        torch = sys.modules.get("torch")
        if torch is not None:
            self._restore_torch(torch, self["torch"] or {"deterministic": False,
                                                         "deterministic_warn_only": False})
        environ = self["environ"]
        if dict(os.environ) != environ:
            for key in [k for k in os.environ if k not in environ]:
                del os.environ[key]
            for key, value in environ.items():
                if os.environ.get(key) != value:
                    os.environ[key] = value

    @staticmethod
    def _restore_torch(torch, settings: dict) -> None:
        if (torch.are_deterministic_algorithms_enabled() != settings["deterministic"]
                or torch.is_deterministic_algorithms_warn_only_enabled()
                != settings["deterministic_warn_only"]):
            deterministic_torch(settings["deterministic"],
                                warn_only=settings["deterministic_warn_only"])
        threads = settings.get("threads")
        if threads is not None and torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


@contextlib.contextmanager
def restored_process_state() -> Iterator[ProcessState]:
    """Undo, on leaving (return or exception), any change to torch's deterministic flag, torch's
    thread count and ``os.environ`` made inside. Yields the snapshot taken on entry."""
    before = ProcessState.capture()
    try:
        yield before
    finally:
        before.restore()


def restores_process_state(func: F) -> F:
    """Decorator: ``func`` runs inside :func:`restored_process_state`."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with restored_process_state():
            return func(*args, **kwargs)
    return wrapper  # type: ignore[return-value]
