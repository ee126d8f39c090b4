"""Entry point of the ``heliocal`` console script: registers every subcommand.

``app`` (the typer application with every subcommand registered) is made on first use:
``from heliocal.cli.main import app``. :func:`main` first asks :mod:`heliocal.cli.rerun`
whether the command is an ``--incremental`` rerun that keeps its previous run, which it answers
without loading typer; every other command goes to ``app``.
"""

from __future__ import annotations

import sys

from heliocal.pipeline.errors import resource_error_message

__all__ = ["app", "main"]


def registered_app():
    """The typer application with every subcommand registered."""
    from heliocal.cli.app import app

    # Each module registers its subcommand(s) on import.
    from heliocal.cli import ingest as _ingest  # noqa: F401
    from heliocal.cli import split as _split  # noqa: F401
    from heliocal.cli import coarse as _coarse  # noqa: F401
    from heliocal.cli import report as _report  # noqa: F401
    from heliocal.cli import simulate as _simulate  # noqa: F401
    from heliocal.cli import hybrid as _hybrid  # noqa: F401
    from heliocal.cli import sweep as _sweep  # noqa: F401
    from heliocal.cli import info as _info  # noqa: F401
    from heliocal.cli import plan as _plan  # noqa: F401
    from heliocal.cli import update as _update  # noqa: F401

    return app


def __getattr__(name: str):
    if name == "app":
        return registered_app()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main() -> None:
    """Run the CLI; an unexpected exception becomes one stderr line (traceback with HELIOCAL_DEBUG=1)."""
    try:
        from heliocal.cli.rerun import run_if_unchanged

        code = run_if_unchanged(sys.argv[1:])
        if code is not None:
            sys.exit(code)
        registered_app()()
    except SystemExit:
        raise
    except KeyboardInterrupt:
        from heliocal.cli.app import INTERRUPTED

        print(f"Error: interrupted (SIGINT); {INTERRUPTED}", file=sys.stderr)
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - the last line of defence against tracebacks
        from heliocal.cli.app import debug_enabled

        if debug_enabled():
            raise
        message = resource_error_message(exc)
        if message is not None:  # the machine's resources or permissions: the user's to fix
            print(f"Error: {' '.join(message.split())}", file=sys.stderr)
            sys.exit(1)
        print(f"Error: internal error {type(exc).__name__}: {' '.join(str(exc).split())} "
              "(a bug in heliocal: rerun with HELIOCAL_DEBUG=1 for the traceback and report it)",
              file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
