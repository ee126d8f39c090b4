"""The batch forms of ``heliocal aim``: ``--schedule FILE`` and ``--date D --every 10min``.

See docs/hybrid.md ("Many aims"). Library: :mod:`heliocal.pipeline.stages.aim_field`.
"""

from __future__ import annotations

import sys
from pathlib import Path

from rich import box
from rich.table import Table

from heliocal.cli.app import emit, stdout
from heliocal.pipeline.errors import ParameterError

__all__ = ["aim_many"]


def _summary(aims, out: Path | None) -> dict:
    ok = aims[aims["status"] == "ok"]
    reasons = aims.loc[aims["status"] != "ok", "reason"].value_counts()
    return {"aims": int(len(aims)), "ok": int(len(ok)), "rejected": int(len(aims) - len(ok)),
            "reasons": {str(k): int(v) for k, v in reasons.items()},
            "heliostats": int(aims["heliostat_id"].nunique()),
            "median_expected_error_mrad": (float(ok["expected_error_mrad"].median())
                                           if len(ok) else None),
            "max_expected_error_mrad": (float(ok["expected_error_mrad"].max())
                                        if len(ok) else None),
            "models": {str(k): int(v) for k, v in ok["model"].value_counts().items()},
            "out": None if out is None else str(out)}


def _human(summary: dict) -> None:
    table = Table(title=f"aim: {summary['aims']} aims of {summary['heliostats']} heliostats -> "
                        f"{summary['out']}", box=box.SIMPLE_HEAD, pad_edge=False)
    table.add_column("status")
    table.add_column("aims", justify="right")
    table.add_row("ok", str(summary["ok"]))
    for reason, n in summary["reasons"].items():
        table.add_row(f"rejected: {reason}", str(n))
    stdout.print(table)
    if summary["ok"]:
        stdout.print(f"expected error: median {summary['median_expected_error_mrad']:.3g} mrad, "
                     f"largest {summary['max_expected_error_mrad']:.3g} mrad; models "
                     + ", ".join(f"{k} {v}" for k, v in summary["models"].items()))


def aim_many(workdir: Path, *, schedule: Path | None, date: str | None, every: str,
             heliostats: list[str] | None, target: str | None, out: Path | None, model: str,
             max_expected_error: float | None, as_json: bool) -> None:
    """Aim a schedule file or a whole day, write the table to ``out`` (CSV on stdout without
    it) and print a summary (stderr when the table goes to stdout)."""
    from heliocal.pipeline.stages.aim_field import (aim_schedule, aims_csv, day_schedule,
                                                    read_schedule, write_aims)

    if (schedule is None) == (date is None):
        raise ParameterError("give one of --schedule FILE or --date DAY for many aims")
    if schedule is not None and (heliostats or target):
        raise ParameterError("--heliostat and --target go with --date; a schedule file names "
                             "its heliostats and targets per row")
    if schedule is not None:
        rows, daylight_only = read_schedule(schedule), False
    else:
        rows, daylight_only = day_schedule(workdir, date, every, heliostats, target), True
    aims = aim_schedule(workdir, rows, model=model, max_expected_error_mrad=max_expected_error,
                        daylight_only=daylight_only)
    if out is None:
        aims_csv(aims, sys.stdout)
        return
    write_aims(aims, out)
    emit(_summary(aims, out), as_json, _human)
