"""``heliocal simulate``: a seeded synthetic field with known ground truth (PAINT layout + logs)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from heliocal.cli.app import JsonFlag, QuietFlag, Seed, command, emit, stdout
from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.vocabulary import DisturbanceKind, SimulatedMounting

DISTURBANCE_KINDS = DisturbanceKind.values()

__all__ = ["simulate_cmd"]


def _parse_range(text: str) -> tuple[int, int]:
    parts = [p.strip() for p in text.split(",")]
    try:
        if len(parts) == 1:
            lo = hi = int(parts[0])
        elif len(parts) == 2:
            lo, hi = int(parts[0]), int(parts[1])
        else:
            raise ValueError(text)
    except ValueError as exc:
        raise ParameterError(f"The 'measurements' parameter of simulate must be MIN,MAX (two "
                             f"integers, e.g. 120,180). Got {text!r} instead.") from exc
    return lo, hi


def _parse_list(text: str) -> tuple[str, ...]:
    return tuple(p.strip() for p in text.split(",") if p.strip())


def _human(summary: dict) -> None:
    table = Table(title=f"simulate -> {summary['out']} (seed {summary['seed']}, noise "
                        f"{summary['noise_mrad']:g} mrad)", show_edge=False)
    for col in ("heliostat", "type", "dynamic", "n", "noise floor", "true static", "nominal"):
        table.add_column(col, justify="left" if col in ("heliostat", "type", "dynamic") else "right")
    for h in summary["heliostats"]:
        table.add_row(h["heliostat_id"], h["kinematic_type"], "yes" if h["dynamic"] else "no",
                      str(h["n_measurements"]), f"{h['noise_floor_mrad']:.4f}",
                      f"{h['error_true_static_mrad']:.4f}", f"{h['error_nominal_mrad']:.3f}")
    stdout.print(table)
    stdout.print("mean error_mrad of the true model (noise floor), of the true geometry without "
                 "the dynamic disturbances, and of the nominal geometry; details in "
                 "ground_truth.json.", markup=False)
    stdout.print("wrote " + ", ".join(summary["files"].values()), markup=False)


@command("simulate")
def simulate_cmd(
    out: Annotated[Path, typer.Option(
        "--out", help="Output folder (new or empty; see --overwrite).", file_okay=False)],
    heliostats: Annotated[int, typer.Option(
        "--heliostats", help="Number of heliostats.")] = 4,
    measurements: Annotated[str, typer.Option(
        "--measurements", help="Measurements per heliostat: MIN,MAX (drawn uniformly).")] = "150,150",
    seed: Seed = 0,
    noise_mrad: Annotated[float, typer.Option(
        "--noise-mrad", help="Focal-spot noise: standard deviation per target axis of the beam "
                             "direction [mrad] (spot noise = distance x angle).")] = 0.2,
    dynamic_fraction: Annotated[float, typer.Option(
        "--dynamic-fraction", help="Share of dynamic heliostats (seasonal tilt, actuator drift, "
                                   "gear error, temperature tilt), 0 to 1.")] = 0.5,
    types: Annotated[str, typer.Option(
        "--types", help="Kinematic types, assigned round-robin: juelich (PAINT layout) and/or "
                        "az-el (ENU log + TOML properties).")] = "juelich",
    deviations: Annotated[str, typer.Option(
        "--deviations", help="Parameters with a true deviation from the nominal geometry: those "
                             "a preset frees (static-6 ... static-28, stone-8) or none.")] = "static-20",
    disturbances: Annotated[str, typer.Option(
        "--disturbances", help="Disturbances of dynamic heliostats, comma-separated: "
                               + ", ".join(DISTURBANCE_KINDS) + ".")] = ",".join(DISTURBANCE_KINDS),
    start: Annotated[str, typer.Option(
        "--start", help="First day of the calibration period (UTC).")] = "2023-01-01",
    end: Annotated[str, typer.Option("--end", help="Day after the period (UTC).")] = "2024-01-01",
    step_fraction: Annotated[float, typer.Option(
        "--step-fraction", help="Share of heliostats with regime steps (1-2 lasting offsets of "
                                "actuator zero points or tilts, 1-4 mrad), 0 to 1.")] = 0.0,
    episode_fraction: Annotated[float, typer.Option(
        "--episode-fraction", help="Share of heliostats with episodes (1-2 offsets of 2-15 mrad "
                                   "that last 1-4 days), 0 to 1.")] = 0.0,
    drift_fraction: Annotated[float, typer.Option(
        "--drift-fraction", help="Share of heliostats whose actuator zero point drifts (1-3 "
                                 "mrad/year from a date on), 0 to 1.")] = 0.0,
    mounting: Annotated[SimulatedMounting, typer.Option(
        "--mounting", help="independent (each heliostat's deviations drawn on its own) or "
                           "field (from its type's distribution: a systematic deviation per "
                           "type, spatially correlated pedestal tilts and positions, and an "
                           "individual part; the ground truth of fit-coarse --prior).")
    ] = SimulatedMounting.independent,
    overwrite: Annotated[bool, typer.Option(
        "--overwrite", help="Replace a previous simulation in --out (only its files are removed).")] = False,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Simulate a synthetic field with known ground truth, in the formats ingest reads."""
    from heliocal.pipeline.models.changes import Changes
    from heliocal.pipeline.models.simulator import simulate_field
    from heliocal.pipeline.stages.simulate import write_field

    field = simulate_field(heliostats, seed=seed, measurements=_parse_range(measurements),
                           kinematic_types=_parse_list(types), dynamic_fraction=dynamic_fraction,
                           disturbances=_parse_list(disturbances), noise_mrad=noise_mrad,
                           deviations=deviations, start=start, end=end,
                           changes=Changes(step_fraction=step_fraction,
                                           episode_fraction=episode_fraction,
                                           drift_fraction=drift_fraction),
                           mounting=mounting.value)
    summary = write_field(field, out, overwrite=overwrite)
    emit(summary, json_, _human)
