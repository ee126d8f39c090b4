"""``heliocal ingest``: sources into measurements.parquet, heliostats.parquet, rejected.parquet."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from heliocal.cli.app import DEFAULT_WORKDIR, JsonFlag, QuietFlag, Workdir, command, emit, stdout
from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.vocabulary import (DEFAULT_BATCH_ROWS, DEFAULT_MAX_SPOT_DISTANCE_M,
                                         DEFAULT_SUN_TOLERANCE_DEG, DEFAULT_TIME_MAX_MARGIN_DAYS,
                                         DEFAULT_TIME_MIN, AzimuthConvention, FocalSpotDetector)


def _choices(choice) -> str:
    """An option's choices from the vocabulary, as --help shows them. The library checks the
    value (IngestOptions.validate): a wrong one is its one-line error, exit code 1."""
    return f"<{'|'.join(choice.values())}>"


def _parse_location(text: Optional[str]):
    if text is None:
        return None
    try:
        lat, lon, alt = (float(x) for x in text.split(","))
    except ValueError as exc:
        raise ParameterError(f"The 'location' parameter of ingest must be LAT,LON,ALT in degrees "
                             f"and metres. Got {text!r} instead.") from exc
    return (lat, lon, alt)


def _human(summary: dict) -> None:
    table = Table(title=f"ingest -> {summary['workdir']}", show_edge=False)
    table.add_column("heliostat")
    table.add_column("kept", justify="right")
    for hid, n in summary["heliostats"].items():
        table.add_row(hid, str(n))
    stdout.print(table)
    stdout.print(f"rows read {summary['rows_read']}, kept {summary['kept']}, "
                 f"rejected {summary['rejected']}")
    for reason, n in summary["rejected_by_reason"].items():
        stdout.print(f"  rejected {reason}: {n}")
    if summary["rejected_by_reason"].get("invalid_heliostat_id"):
        from heliocal.pipeline.io.validation import invalid_id_message

        stdout.print(invalid_id_message(summary["rejected_by_reason"]["invalid_heliostat_id"]))


@command("ingest", writes=True)
def ingest_cmd(
    sources: Annotated[list[Path], typer.Argument(help="PAINT folders and/or CSV/Parquet logs.")],
    workdir: Workdir = DEFAULT_WORKDIR,
    tower: Annotated[Optional[Path], typer.Option(
        help="Plant tower-measurements.json (default: found beside or above the source).")] = None,
    properties: Annotated[Optional[Path], typer.Option(
        help="Heliostat properties: a PAINT folder, or a CSV/TOML file (required for ENU logs).")] = None,
    focal_spot: Annotated[str, typer.Option(
        metavar=_choices(FocalSpotDetector),
        help="PAINT focal-spot detector (a row without it falls back to the other).")
    ] = FocalSpotDetector.utis.value,
    max_spot_distance: Annotated[float, typer.Option(
        help="Reject focal spots farther than this from their target centre [m].")
    ] = DEFAULT_MAX_SPOT_DISTANCE_M,
    sun_tolerance: Annotated[float, typer.Option(
        help="Flag rows whose logged sun differs from NREL SPA by more than this [deg].")
    ] = DEFAULT_SUN_TOLERANCE_DEG,
    azimuth_convention: Annotated[str, typer.Option(
        metavar=_choices(AzimuthConvention),
        help="Logged sun azimuth convention: south (0 = south, + east) or north-clockwise "
             "(0 = north, + east).")] = AzimuthConvention.south.value,
    timezone: Annotated[Optional[str], typer.Option(
        help="Time zone of timestamps that carry none (e.g. Europe/Berlin).")] = None,
    location: Annotated[Optional[str], typer.Option(
        help="Plant location LAT,LON,ALT for ENU logs (for NREL SPA sun positions).")] = None,
    date_format: Annotated[Optional[str], typer.Option(
        help="strptime format of the timestamps, e.g. '%d.%m.%Y %H:%M:%S%z'; needed when they "
             "write day and month as numbers first (02.03.2023), which is ambiguous.")] = None,
    time_min: Annotated[str, typer.Option(
        help="Reject measurements before this time (implausible_timestamp).")] = DEFAULT_TIME_MIN,
    time_max: Annotated[Optional[str], typer.Option(
        help="Reject measurements after this time (default: now + "
             f"{DEFAULT_TIME_MAX_MARGIN_DAYS} day).")] = None,
    batch_rows: Annotated[int, typer.Option(
        help="Rows of a log read and validated at a time; peak memory grows with it, not with the "
             "log (a longer log is sorted by heliostat in a hidden folder of the workdir). "
             "The artifacts do not depend on it.", min=1)] = DEFAULT_BATCH_ROWS,
    append: Annotated[bool, typer.Option(
        "--append", help="Add the sources' rows to the work directory's measurements instead of "
        "replacing them (rows already ingested are rejected as duplicate_of_ingested_row).")
    ] = False,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Read calibration logs into the canonical measurement table (nothing is dropped silently)."""
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.stages.ingest import run_ingest

    opts = IngestOptions(tower=tower, properties=properties, focal_spot=focal_spot,
                         max_spot_distance_m=max_spot_distance, sun_tolerance_deg=sun_tolerance,
                         azimuth_convention=azimuth_convention, timezone=timezone,
                         location=_parse_location(location), date_format=date_format,
                         time_min=time_min, time_max=time_max)
    summary = run_ingest(sources, workdir, opts, batch_rows=batch_rows, append=append)
    emit(summary, json_, _human)
