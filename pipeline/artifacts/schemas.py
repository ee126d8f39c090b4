"""The canonical tables written by ``ingest``: measurements, heliostats and rejected rows.

These schemas are the contract every later stage reads. Other stages declare their own
artifacts' schemas in their modules; :func:`nomenclature_markdown` renders all of them into
``docs/nomenclature.md`` (a test keeps that file in sync).
"""

from __future__ import annotations

import re

from .store import ArtifactSchema, Column

__all__ = ["MEASUREMENTS", "HELIOSTATS", "REJECTED", "REJECTION_REASONS", "HELIOSTAT_ID_RE",
           "HELIOSTAT_ID_RULE", "heliostat_id_problem", "suggest_heliostat_id", "all_schemas",
           "nomenclature_markdown"]

#: What a heliostat id may be. Ids become file names (``hybrid/<mode>/<id>.pt``, report figures),
#: so ingest keeps only ids that are safe and portable as such: 1 to 64 ASCII letters, digits,
#: ``_``, ``-`` and ``.``, the first a letter, digit or ``_`` (not ``.``: hidden files, ``..``;
#: not ``-``: read as an option on a command line).
HELIOSTAT_ID_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
HELIOSTAT_ID_RULE = ("1-64 ASCII letters, digits, '_', '-' or '.', starting with a letter, digit "
                     "or '_'")


def heliostat_id_problem(hid) -> str | None:
    """Why ``hid`` is not a valid heliostat id (see :data:`HELIOSTAT_ID_RE`), or ``None``."""
    if not isinstance(hid, str):
        return f"it is a {type(hid).__name__}, not text"
    if HELIOSTAT_ID_RE.fullmatch(hid):
        return None
    if len(hid) > 64:
        return f"it has {len(hid)} characters, more than 64"
    if hid[:1] in (".", "-"):
        return f"it starts with {hid[0]!r}"
    bad = sorted({c for c in hid if not (c.isascii() and (c.isalnum() or c in "_.-"))})
    return "it contains " + ", ".join(repr(c) for c in bad[:5]) + (" ..." if len(bad) > 5 else "")


def suggest_heliostat_id(hid: str) -> str:
    """A valid id close to ``hid``: other characters become ``_``, leading ``.``/``-``/``_`` runs
    are dropped, cut to 64 characters (``"../../x/pwned"`` -> ``"x_pwned"``)."""
    text = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(hid))
    text = re.sub(r"^[._-]+", "", text)[:64]
    return text or "H1"


C = Column

MEASUREMENTS = ArtifactSchema(
    name="measurements",
    filename="measurements.parquet",
    producer="ingest",
    sort_by=("heliostat_id", "timestamp", "measurement_id"),
    extra_prefixes=("env_", "qa_"),
    description="One row per kept calibration measurement (camera-target method), all positions in "
                "ENU metres relative to the plant reference point. A log's extra numeric columns "
                "are kept as `env_<name>`; with them comes `qa_env_blanked`: the env cells of the "
                "row that were blanked because they are infinite or beyond 1e100 in magnitude "
                "(`env_x=inf; ...`, empty if none).",
    columns=(
        C("heliostat_id", "string", "", "Heliostat name, e.g. BE36."),
        C("measurement_id", "string", "", "The source's own id of the measurement (PAINT calibration "
          "id or the log's sample id), unique per heliostat."),
        C("timestamp", "timestamp", "UTC", "Time of the measurement; missing where the source has none.",
          nullable=True),
        C("axis_1_steps", "float64", "steps", "Motor position of actuator 1."),
        C("axis_2_steps", "float64", "steps", "Motor position of actuator 2."),
        C("sun_azimuth_deg", "float64", "deg", "Sun azimuth, 0 = south, positive toward east."),
        C("sun_elevation_deg", "float64", "deg", "Apparent sun elevation above the horizon."),
        C("sun_e", "float64", "1", "East component of the unit vector toward the sun."),
        C("sun_n", "float64", "1", "North component of the unit vector toward the sun."),
        C("sun_u", "float64", "1", "Up component of the unit vector toward the sun."),
        C("sun_source", "string", "", "`log` (angles from the source) or `spa` (computed with "
          "NREL SPA from timestamp and plant location)."),
        C("target_name", "string", "", "Calibration target the heliostat aimed at."),
        C("target_e_m", "float64", "m", "Target centre (aim point), east."),
        C("target_n_m", "float64", "m", "Target centre (aim point), north."),
        C("target_u_m", "float64", "m", "Target centre (aim point), up."),
        C("target_normal_e", "float64", "1", "Unit normal of the target plane, east."),
        C("target_normal_n", "float64", "1", "Unit normal of the target plane, north."),
        C("target_normal_u", "float64", "1", "Unit normal of the target plane, up."),
        C("focal_spot_e_m", "float64", "m", "Measured focal-spot centroid, east."),
        C("focal_spot_n_m", "float64", "m", "Measured focal-spot centroid, north."),
        C("focal_spot_u_m", "float64", "m", "Measured focal-spot centroid, up."),
        C("focal_spot_source", "string", "", "Detector of the centroid: `utis`, `helios` or `log`."),
        C("heliostat_e_m", "float64", "m", "Heliostat position (pedestal reference), east."),
        C("heliostat_n_m", "float64", "m", "Heliostat position, north."),
        C("heliostat_u_m", "float64", "m", "Heliostat position, up."),
        C("source_file", "string", "", "File the row came from."),
        C("source_row", "int64", "", "Row in that file (1-based data row; PAINT: 1)."),
        C("qa_sun_spa_diff_deg", "float64", "deg", "Angle between the logged sun vector and NREL SPA "
          "for the timestamp (missing without timestamp or when the sun came from SPA).",
          nullable=True),
        C("qa_sun_mismatch", "bool", "", "True where qa_sun_spa_diff_deg exceeds the tolerance "
          "(default 0.1 deg): kept, but worth a look."),
    ),
)

HELIOSTATS = ArtifactSchema(
    name="heliostats",
    filename="heliostats.parquet",
    producer="ingest",
    sort_by=("heliostat_id",),
    description="One row per heliostat: kinematic type and the nominal geometry the coarse model "
                "starts from. Angles follow docs/kinematics.md (PAINT's axis-1 initial angle is "
                "stored with ARTIST's -pi/2 shift applied).",
    columns=(
        C("heliostat_id", "string", "", "Heliostat name."),
        C("kinematic_type", "string", "", "`juelich` (PAINT/ARTIST, two linear actuators), `az-el` "
          "(azimuth-elevation, ideal actuators) or `target-aligned`."),
        C("actuator_type", "string", "", "`linear` or `ideal`."),
        C("properties_source", "string", "", "Where the nominal geometry came from (file path or "
          "`default-juelich`)."),
        C("heliostat_e_m", "float64", "m", "Position, east."),
        C("heliostat_n_m", "float64", "m", "Position, north."),
        C("heliostat_u_m", "float64", "m", "Position, up."),
        C("latitude_deg", "float64", "deg", "WGS84 latitude (missing for ENU sources).", nullable=True),
        C("longitude_deg", "float64", "deg", "WGS84 longitude.", nullable=True),
        C("altitude_m", "float64", "m", "WGS84 ellipsoidal height.", nullable=True),
        C("initial_orientation_e", "float64", "1", "Mirror normal at zero joint angles, east."),
        C("initial_orientation_n", "float64", "1", "Mirror normal at zero joint angles, north."),
        C("initial_orientation_u", "float64", "1", "Mirror normal at zero joint angles, up."),
        *[C(f"{j}_translation_{a}_m", "float64", "m", f"Nominal {j.replace('_', ' ')} translation, "
            f"{ {'e': 'east', 'n': 'north', 'u': 'up'}[a]}.")
          for j in ("joint_1", "joint_2", "concentrator") for a in "enu"],
        *[c for i in (1, 2) for c in (
            C(f"axis_{i}_increment", "float64", "steps/m", f"Actuator {i}: motor steps per metre of "
              "stroke (linear).", nullable=True),
            C(f"axis_{i}_initial_stroke_length_m", "float64", "m", f"Actuator {i}: stroke at 0 steps.",
              nullable=True),
            C(f"axis_{i}_offset_m", "float64", "m", f"Actuator {i}: offset.", nullable=True),
            C(f"axis_{i}_pivot_radius_m", "float64", "m", f"Actuator {i}: pivot radius.", nullable=True),
            C(f"axis_{i}_initial_angle_rad", "float64", "rad", f"Actuator {i}: initial angle "
              "(ARTIST's internal convention).", nullable=True),
            C(f"axis_{i}_clockwise", "bool", "", f"Actuator {i}: clockwise axis movement."),
            C(f"axis_{i}_min_steps", "float64", "steps", f"Actuator {i}: lowest allowed motor position."),
            C(f"axis_{i}_max_steps", "float64", "steps", f"Actuator {i}: highest allowed motor position."),
            C(f"axis_{i}_gear_ratio_steps_per_rad", "float64", "steps/rad", f"Actuator {i}: gear ratio "
              "(ideal actuators).", nullable=True),
            C(f"axis_{i}_angle_offset_rad", "float64", "rad", f"Actuator {i}: joint angle at 0 steps "
              "(ideal actuators).", nullable=True),
        )],
        C("primary_axis_e", "float64", "1", "Target-aligned type: primary axis (unit, toward the "
          "target), east.", nullable=True),
        C("primary_axis_n", "float64", "1", "Primary axis, north.", nullable=True),
        C("primary_axis_u", "float64", "1", "Primary axis, up.", nullable=True),
        C("n_measurements", "int64", "", "Kept measurements of this heliostat."),
    ),
)

#: Reasons a row can be rejected, with their meaning (rejected.parquet's ``reason`` column).
REJECTION_REASONS = {
    "missing_value": "a required field is empty",
    "unparsable_number": "a numeric field is not a number (or is NaN or infinite)",
    "unparsable_timestamp": "the timestamp cannot be read as a UTC time",
    "steps_out_of_range": "a motor position is outside the actuator's range",
    "sun_below_horizon": "the sun elevation is not above the horizon",
    "duplicate_measurement_id": "the heliostat already has a measurement with this id",
    "unknown_target": "the target name is not in the tower/targets file",
    "unknown_heliostat": "no properties for this heliostat",
    "focal_spot_far_from_target": "the focal spot lies implausibly far from its target",
    "malformed_file": "the file (one PAINT measurement) cannot be parsed",
    "sun_angle_out_of_range": "a sun angle is outside its physical range",
    "invalid_heliostat_id": "the heliostat id is not " + HELIOSTAT_ID_RULE + " (it would be "
                            "unsafe as a file name): rename the heliostat in the source",
    # plausibility of timestamps (ingest --time-min/--time-max/--date-format)
    "implausible_timestamp": "the timestamp lies outside the plausible range of the instrument "
                             "(default 1990 to now + 1 day; ingest --time-min, --time-max)",
    "ambiguous_timestamp": "the timestamp writes day and month as numbers in an order heliocal "
                           "cannot tell (02.03.2023, 3/2/2023): give ingest --date-format",
}

REJECTED = ArtifactSchema(
    name="rejected",
    filename="rejected.parquet",
    producer="ingest",
    sort_by=("source_file", "source_row"),
    description="Every input row that ingest did not keep, with the reason. Together with "
                "measurements.parquet it accounts for every input row.",
    columns=(
        C("source_file", "string", "", "File the row came from."),
        C("source_row", "int64", "", "Row in that file (1-based data row; PAINT: 1)."),
        C("heliostat_id", "string", "", "Heliostat, where readable.", nullable=True),
        C("measurement_id", "string", "", "Measurement id, where readable.", nullable=True),
        C("reason", "string", "", "One of the reason codes (see REJECTION_REASONS)."),
        C("detail", "string", "", "What exactly was wrong, in words."),
        C("raw", "string", "", "The raw row as JSON, so nothing is lost."),
    ),
)


def all_schemas() -> list[ArtifactSchema]:
    """Every artifact schema of heliocal (imports the stage modules that declare theirs)."""
    import importlib

    schemas = [MEASUREMENTS, HELIOSTATS, REJECTED]
    for module in ("stages.split", "models.coarse", "models.hybrid", "stages.sweep"):
        try:
            mod = importlib.import_module(f"heliocal.pipeline.{module}")
        except ImportError:
            continue
        schemas.extend(getattr(mod, "SCHEMAS", ()))
    return schemas


def nomenclature_markdown() -> str:
    """Render the nomenclature (every artifact column with unit and meaning) as Markdown."""
    lines = ["# Nomenclature", "",
             "Generated from the declared schemas by `python -m heliocal.pipeline.artifacts.schemas`; "
             "a test keeps it in sync.", "",
             "Conventions: ENU metres relative to the plant reference point; sun azimuth 0 = south, "
             "positive toward east; sun vector e = cos(el) sin(az), n = -cos(el) cos(az), "
             "u = sin(el); angular errors in milliradians.", ""]
    for s in all_schemas():
        lines += [f"## {s.filename} (written by `heliocal {s.producer}`)", "", s.description, ""]
        if s.extra_prefixes:
            lines += ["Extra columns allowed with prefixes: "
                      + ", ".join(f"`{p}*`" for p in s.extra_prefixes) + ".", ""]
        lines += ["| column | type | unit | meaning |", "|---|---|---|---|"]
        for c in s.columns:
            null = " (may be missing)" if c.nullable else ""
            lines.append(f"| `{c.name}` | {c.dtype} | {c.unit} | {c.description}{null} |")
        lines.append("")
    lines += ["## Rejection reasons", "", "| reason | meaning |", "|---|---|"]
    lines += [f"| `{k}` | {v} |" for k, v in REJECTION_REASONS.items()]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # pragma: no cover
    print(nomenclature_markdown(), end="")
