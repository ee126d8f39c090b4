"""The schema registry: every artifact heliocal writes, declared once, in stage order.

``ingest`` writes measurements, heliostats and rejected rows; ``split-knn`` the split;
``fit-coarse`` the coarse parameters and predictions; ``fit-hybrid`` its predictions; ``sweep``
the sweep, the selection and the selected model's predictions. These schemas are the contract
every stage reads and writes through; :func:`nomenclature_markdown` renders all of them into
``docs/nomenclature.md`` (a test keeps that file in sync).
"""

from __future__ import annotations

import dataclasses

from .ids import (HELIOSTAT_ID_RE, HELIOSTAT_ID_RULE, WINDOWS_RESERVED_NAMES,
                  heliostat_id_problem, suggest_heliostat_id)
from .schemas_prior import COARSE_PRIOR_COLUMNS, FIELD_PRIOR
from .table import ArtifactSchema, Column

__all__ = ["MEASUREMENTS", "HELIOSTATS", "REJECTED", "SPLIT", "COARSE_PARAMS", "COARSE_PREDICTIONS",
           "REGIMES", "REGIME_PARAMS", "ROLLING_ORIGIN", "FIELD_PRIOR", "HYBRID_PREDICTIONS", "SWEEP", "SELECTION",
           "SELECTED_PREDICTIONS", "PLAN", "REJECTION_REASONS", "HELIOSTAT_ID_RE",
           "HELIOSTAT_ID_RULE", "heliostat_id_problem", "suggest_heliostat_id", "all_schemas",
           "WINDOWS_RESERVED_NAMES", "nomenclature_markdown"]

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
        C("renovation_start", "timestamp", "UTC", "Start of the last renovation (PAINT's "
          "`renovation` property: midnight of its first day); fit-coarse puts a known regime "
          "break there. Missing if the source has none.", nullable=True),
        C("renovation_end", "timestamp", "UTC", "End of that renovation (midnight after its "
          "last day).", nullable=True),
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
    "duplicate_of_ingested_row": "duplicate of an ingested row: `ingest --append` met a row "
                                 "identical (but for its source file and row) to one the work "
                                 "directory already holds",
    "unknown_target": "the target name is not in the tower/targets file",
    "unknown_heliostat": "no properties for this heliostat",
    "focal_spot_far_from_target": "the focal spot lies implausibly far from its target",
    "malformed_file": "the file (one PAINT measurement) cannot be parsed",
    "sun_angle_out_of_range": "a sun angle is outside its physical range",
    "invalid_heliostat_id": "the heliostat id is not " + HELIOSTAT_ID_RULE + ", or it is a device "
                            "name Windows reserves (CON, PRN, AUX, NUL, COM1-9, LPT1-9, also "
                            "with an extension such as NUL.txt; it would be unsafe or impossible "
                            "as a file name): rename the heliostat in the source",
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


SPLIT = ArtifactSchema(
    name="split",
    filename="split.parquet",
    producer="split-knn",
    sort_by=("heliostat_id", "measurement_id"),
    description="One row per measurement of every heliostat that was split: its set (train, "
                "validation, test or unused) and the distances in sun position the split was "
                "judged by. Heliostats with too few measurements are absent (the stage warns).",
    columns=(
        C("heliostat_id", "string", "", "Heliostat name."),
        C("measurement_id", "string", "", "Measurement id (as in measurements.parquet)."),
        C("split", "string", "", "`train`, `validation`, `test`, or `unused` (a training "
          "candidate dropped by the training-size limit): the split that selects models."),
        C("time_split", "string", "", "The forward-in-time split beside it, with the same sizes: "
          "`test` the latest n_test measurements, `validation` the n_val before them, `train` "
          "the earlier ones (`unused`: dropped by the training-size limit, kNN rule). Every "
          "model is evaluated on it too, trained on its `train` rows only. Missing for a "
          "measurement without timestamp and for every measurement of a heliostat with too few "
          "timestamps (its forward-in-time errors are n/a).", nullable=True),
        C("knn_distance_deg", "float64", "deg", "Mean distance in sun position to the k nearest "
          "other measurements of the same heliostat (k and metric as recorded in the "
          "provenance; computed for every method)."),
        C("knn_rank", "int64", "", "Rank by knn_distance_deg within the heliostat, 0 = largest "
          "distance; ties broken by measurement_id."),
        C("nearest_train_distance_deg", "float64", "deg", "Distance in sun position to the "
          "nearest training measurement of the same heliostat (for a training row: to the "
          "nearest other training row)."),
        C("method", "string", "", "Split method: `knn`, `random`, `time`, `azimuth`, "
          "`solstice`, `balanced` or `high-variance`."),
        C("metric", "string", "", "Distance metric of the distance columns: `euclidean` "
          "(degrees in the azimuth-elevation plane) or `great-circle` (angle between sun "
          "vectors)."),
        C("sun_azimuth_deg", "float64", "deg", "Sun azimuth (copied from measurements.parquet, "
          "so the split can be re-restricted and plotted on its own)."),
        C("sun_elevation_deg", "float64", "deg", "Sun elevation (copied from "
          "measurements.parquet)."),
    ),
)

COARSE_PARAMS = ArtifactSchema(
    name="coarse_params",
    filename="coarse_params.parquet",
    producer="fit-coarse",
    sort_by=("heliostat_id", "preset", "parameter_index"),
    description="Per heliostat, preset and kinematic parameter: nominal and fitted value, standard "
                "error, free or fixed, plus the fit's diagnostics (repeated on each row of a fit).",
    columns=(
        C("heliostat_id", "string", "", "Heliostat."),
        C("preset", "string", "", "Parameter preset of the fit (static-6 ... static-28, stone-8), "
          "a regime-aware candidate on the selected preset (`<preset>+offsets`, "
          "`<preset>+drift`; regime_params.parquet): its `fitted` values are the latest "
          "regime's parameters, or the field-prior geometry `<preset>+field-prior` (the "
          "nominal geometry moved by the field prior's mean of `<preset>`, field_prior.parquet; "
          "not fitted: a candidate of every heliostat's selection, and the model of a heliostat "
          "without training rows, `n_train` 0)."),
        C("selected", "bool", "", "True for the preset used downstream (chosen by validation error "
          "with --preset auto)."),
        C("parameter_index", "int64", "", "Position in the 28-parameter vector."),
        C("parameter", "string", "", "Parameter name (unit in the name; see docs/kinematics.md)."),
        C("unit", "string", "", "Unit of the parameter."),
        C("nominal", "float64", "", "Nominal value from heliostats.parquet."),
        C("fitted", "float64", "", "Fitted value (nominal where fixed)."),
        C("std_error", "float64", "", "Standard error from the Jacobian (NaN where fixed).",
          nullable=True),
        C("free", "bool", "", "Freed by the preset."),
        C("determined", "bool", "", "False where the data cannot determine it (std error > half "
          "the prior sigma)."),
        C("fit_iterations", "int64", "", "Jacobian evaluations of the LM solve (robust start excluded)."),
        C("fit_cost", "float64", "mrad^2", "Final cost: half the sum of squared residuals "
          "(missing for a field-prior geometry, which is not fitted).", nullable=True),
        C("fit_condition_number", "float64", "", "Condition number of the scaled Jacobian "
          "(missing for a field-prior geometry).", nullable=True),
        C("fit_status", "string", "", "Solver message."),
        C("fit_implausible", "string", "", "Parameters corrected by more than a plausible amount "
          "(empty if none)."),
        C("fit_degenerate", "string", "", "Why the heliostat's training rows cannot determine "
          "the parameters of the simplest preset (static-6): all rows identical, or too little "
          "spread in sun position; its errors then say nothing about accuracy (empty if the "
          "data are fine)."),
        C("n_train", "int64", "", "Training measurements."),
        C("train_error_mrad", "float64", "mrad", "Mean error on the training rows (missing for "
          "the field-prior geometry of a heliostat without training rows).", nullable=True),
        C("val_error_mrad", "float64", "mrad", "Mean error on the validation rows (NaN if none).",
          nullable=True),
        C("test_error_mrad", "float64", "mrad", "Mean error on the test rows (NaN if none).",
          nullable=True),
        C("time_fitted", "float64", "", "The parameter fitted again, the same way, on the time "
          "split's training rows outside detected episodes (split.parquet `time_split`; a "
          "regime-aware candidate with the same regimes, its latest regime's value); missing "
          "where the heliostat has no time split.", nullable=True),
        C("time_val_error_mrad", "float64", "mrad", "Mean error of that time-split fit on the "
          "time split's validation rows outside detected episodes (missing: n/a); the selection "
          "weighs it beside `val_error_mrad` (docs/split.md, \"Choosing forward-aware\").",
          nullable=True),
        C("time_test_error_mrad", "float64", "mrad", "Its mean error on the time split's test "
          "rows, the latest measurements (missing: n/a).", nullable=True),
        *COARSE_PRIOR_COLUMNS,
    ),
)

COARSE_PREDICTIONS = ArtifactSchema(
    name="coarse_predictions",
    filename="coarse_predictions.parquet",
    producer="fit-coarse",
    sort_by=("heliostat_id", "model", "measurement_id"),
    description="Per measurement and model (nominal geometry and each fitted preset): the errors "
                "defined once in heliocal.pipeline.physics.metrics.",
    columns=(
        C("heliostat_id", "string", "", "Heliostat."),
        C("measurement_id", "string", "", "Measurement."),
        C("split", "string", "", "train, validation, test or unused (all train without split.parquet)."),
        C("model", "string", "", "`nominal`, the preset name or a regime-aware candidate "
          "(`<preset>+offsets`, `<preset>+drift`: each row at its regime's parameters); hybrid "
          "stages add theirs."),
        C("selected", "bool", "", "True for the model used downstream."),
        C("error_mrad", "float64", "mrad", "Angle between predicted and measured mirror normal."),
        C("beam_error_mrad", "float64", "mrad", "Angle between the predicted reflected beam and the "
          "direction to the measured spot."),
        C("spot_offset_horizontal_m", "float64", "m", "Predicted minus measured spot on the target "
          "plane, horizontal axis (east for a north-facing target)."),
        C("spot_offset_vertical_m", "float64", "m", "Same, vertical axis (up)."),
        C("spot_offset_m", "float64", "m", "Distance between predicted and measured spot on the "
          "target plane."),
        C("time_error_mrad", "float64", "mrad", "error_mrad of the same model (preset, "
          "regime-aware candidate, or the selected hybrid configuration) trained again on the "
          "time split's training rows (split.parquet `time_split`), so that on the time split's "
          "validation and test rows it is an honest forward-in-time error; missing for the "
          "nominal geometry, for hybrids other than the selected one and where the heliostat "
          "has no time split.", nullable=True),
    ),
)

REGIMES = ArtifactSchema(
    name="regimes",
    filename="regimes.parquet",
    producer="fit-coarse",
    sort_by=("heliostat_id", "start", "kind", "measurement_id"),
    description="Per heliostat, its regimes, episodes and outliers, found on the selected coarse "
                "fit's residuals in time order (training and validation rows; test rows are "
                "assigned by time): change points by PELT with a BIC penalty scaled by the robust "
                "residual noise, renovation dates as known breaks, isolated outliers by a robust "
                "score (heliocal.pipeline.models.regimes says how). One row per segment "
                "(`regime`, `episode`) and per outlier; outliers are flagged, never dropped.",
    columns=(
        C("heliostat_id", "string", "", "Heliostat."),
        C("kind", "string", "", "`regime` (the heliostat's geometry between two breaks), "
          "`episode` (a segment of at most a week between two others: off for a few days) or "
          "`outlier` (one row far from its segment)."),
        C("regime", "int64", "", "Regime number, 0 = oldest; an episode and an outlier carry "
          "the number of the regime they interrupt."),
        C("start", "timestamp", "UTC", "First measurement of the segment (outlier: its time)."),
        C("end", "timestamp", "UTC", "Last measurement of the segment (outlier: its time)."),
        C("cause", "string", "", "What starts the segment: `start` (first), `renovation` (a "
          "PAINT renovation date), `detected` (a change point), `outlier`."),
        C("n_rows", "int64", "", "Measurements of the segment that the detection read."),
        C("measurement_id", "string", "", "The outlier's measurement (missing for segments).",
          nullable=True),
        C("center_horizontal_mrad", "float64", "mrad", "Median residual of the mirror normal "
          "along the target's horizontal axis on the segment (outlier: its residual)."),
        C("center_vertical_mrad", "float64", "mrad", "Same, vertical axis."),
        C("step_mrad", "float64", "mrad", "Size of the break at the segment's start: distance "
          "between its median residual and the previous segment's (outlier: its distance from "
          "its segment's median); missing for the first segment.", nullable=True),
        C("evidence", "float64", "", "Break: decrease of the l2 cost by the break divided by "
          "the penalty (> 1: PELT would break there; a renovation may show less); outlier: its "
          "robust distance in noise units; missing for the first segment.", nullable=True),
        C("noise_mrad", "float64", "mrad", "Robust noise of the heliostat's residuals (mean of "
          "the two components)."),
        C("error_mrad", "float64", "mrad", "Mean error of the finally selected coarse model on "
          "the rows of every split from start to end (outlier: its row); rows of a detected "
          "episode are left out of that model's training and of its selection, so an episode "
          "reports here the error no geometry of the heliostat can remove.", nullable=True),
    ),
)

REGIME_PARAMS = ArtifactSchema(
    name="regime_params",
    filename="regime_params.parquet",
    producer="fit-coarse",
    sort_by=("heliostat_id", "model", "regime", "parameter"),
    description="Per heliostat with a detected or renovation break, regime-aware candidate "
                "(`<preset>+offsets`: per-regime offsets of the actuator zero points and small "
                "tilts on the selected preset's shared geometry; `<preset>+drift`: the same with "
                "zero points linear in time per regime), regime and moved parameter: its offset "
                "and drift (heliocal.pipeline.models.regime_fit says how). A candidate is "
                "selected only if it beats the plain fit by the sweep's 20 % margin on validation; "
                "its latest regime's parameters are then coarse_params' `fitted` values.",
    columns=(
        C("heliostat_id", "string", "", "Heliostat."),
        C("model", "string", "", "`<preset>+offsets` or `<preset>+drift` (as in coarse_params)."),
        C("selected", "bool", "", "True if the candidate is the heliostat's selected coarse model."),
        C("regime", "int64", "", "Regime number (regimes.parquet)."),
        C("fitted_regime", "int64", "", "The regime whose training rows determined the offsets "
          "this regime uses (itself, or the one before when it has too few training rows)."),
        C("start", "timestamp", "UTC", "First measurement of the regime.", nullable=True),
        C("end", "timestamp", "UTC", "Last measurement of the regime.", nullable=True),
        C("n_train", "int64", "", "Training rows (outside episodes) of `fitted_regime`."),
        C("parameter", "string", "", "Parameter with an offset (unit in the name)."),
        C("offset_rad", "float64", "rad", "Offset of the parameter in this regime, relative to the "
          "shared geometry (0 for the reference regime)."),
        C("value_rad", "float64", "rad", "The parameter's value in this regime: shared geometry "
          "plus offset (with a drift: at `drift_reference`)."),
        C("drift_rad_per_year", "float64", "rad/year", "Rate of the parameter in this regime "
          "(0 where it does not drift)."),
        C("drift_reference", "timestamp", "UTC", "Time at which the drift adds nothing (mean "
          "time of the regime's training rows); missing where it does not drift.", nullable=True),
        C("drift_from", "timestamp", "UTC", "First training row of the regime whose rows fitted "
          "the drift: before it the drift is held at its value there "
          "(regime_fit.DRIFT_EXTRAPOLATION_DAYS); missing where it does not drift.", nullable=True),
        C("drift_to", "timestamp", "UTC", "Last training row of that regime: after it the drift "
          "is held (no extrapolation); missing where it does not drift.", nullable=True),
        C("latest", "bool", "", "True for the heliostat's latest regime (the one `aim` uses)."),
    ),
)

ROLLING_ORIGIN = ArtifactSchema(
    name="rolling_origin",
    filename="rolling_origin.parquet",
    producer="fit-coarse",
    sort_by=("heliostat_id", "measurement_id"),
    description="The rolling-origin (prequential) evaluation of fit-coarse's selected preset: at "
                "each origin (a calibration day with enough earlier rows; at most "
                "`--rolling-origins` per heliostat, spread over its history) the preset is "
                "fitted again on every row before that day (a regime-aware selection: the rows "
                "since its latest break) and scores that day's rows: the next-day error of a "
                "heliostat recalibrated every calibration day "
                "(heliocal.pipeline.stages.rolling says how).",
    columns=(
        C("heliostat_id", "string", "", "Heliostat."),
        C("measurement_id", "string", "", "The row scored."),
        C("origin_date", "timestamp", "UTC", "The calibration day (UTC midnight) whose rows are "
          "scored by the fit on the rows before it."),
        C("model", "string", "", "The preset fitted at the origin (the selected model's "
          "geometry)."),
        C("n_train", "int64", "", "Rows the origin's fit used."),
        C("days_since_last_row", "float64", "d", "Time from the fit's last row to the row "
          "scored [days]."),
        C("error_mrad", "float64", "mrad", "The row's error under the origin's fit (the next-day "
          "error)."),
    ),
)


HYBRID_PREDICTIONS = dataclasses.replace(
    COARSE_PREDICTIONS,
    name="hybrid_predictions",
    filename="hybrid_predictions.parquet",
    producer="fit-hybrid",
    description="Per measurement and fitted mode (hybrid, nn-only, pretrained-nn, gp): the errors "
                "defined once in heliocal.pipeline.physics.metrics, same columns as "
                "coarse_predictions.parquet; `model` is the mode, `selected` is True for the "
                "hybrid mode (the one `aim` uses).",
)

SWEEP = ArtifactSchema(
    name="sweep", filename="sweep.parquet", producer="sweep",
    sort_by=("heliostat_id", "model", "n_train", "weight_decay", "seed"),
    volatile=("wall_time_s",),
    description="One row per heliostat, model, training size, weight decay and seed: mean and "
                "median error_mrad per split (means over the split's rows). Every heliostat has "
                "its full-size rows (fit-coarse's presets and the hybrid candidates of the "
                "selection); the heliostats of the training-size study also smaller sizes and "
                "the baselines.",
    columns=(
        C("heliostat_id", "string", "", "Heliostat."),
        C("model", "string", "", "Coarse preset name (at the full size: fit-coarse's fit of "
          "it; at smaller sizes the study's refit as fit-coarse fits it, under the field prior "
          "fit-coarse gave the heliostat where it had one), `<preset>+no-field-prior` (the "
          "study's fit of a preset without that field prior, at every size; only where "
          "fit-coarse fitted the preset under one), `<preset>+field-prior` (the field-prior "
          "geometry, full size), `hybrid` (the config's Fourier bands), `hybrid-octaves` "
          "(octave bands), `gp` "
          "(the GP correction; `gp-sun` its sun-only structure beside one with time), "
          "`nn-only` or `pretrained-nn`."),
        C("n_train", "int64", "", "Training rows (largest kNN distance first)."),
        C("weight_decay", "float64", "", "Weight decay of the hybrid (NaN for other models).",
          nullable=True),
        C("seed", "int64", "", "Seed of the network's initial weights (0 for coarse presets)."),
        C("train_error_mrad", "float64", "mrad", "Mean error on the training rows (of this "
          "training size)."),
        C("train_median_error_mrad", "float64", "mrad", "Median error on the training rows."),
        C("val_error_mrad", "float64", "mrad", "Mean error on the validation rows.", nullable=True),
        C("val_median_error_mrad", "float64", "mrad", "Median on validation.", nullable=True),
        C("test_error_mrad", "float64", "mrad", "Mean error on the test rows.", nullable=True),
        C("test_median_error_mrad", "float64", "mrad", "Median on test.", nullable=True),
        C("test_train_distance_deg", "float64", "deg", "Mean distance of the test rows to their "
          "nearest training row (sun angles).", nullable=True),
        C("base_preset", "string", "", "Coarse preset under the hybrid / the preset itself."),
        C("wall_time_s", "float64", "s", "Wall time of this member's share of the training (0 "
          "for fit-coarse's fits, which the sweep reads)."),
        C("fade_length_deg", "float64", "deg", "Sun fade length of a fine model of the "
          "production selection, chosen on its distance-weighted validation rows (inf: no "
          "fade; docs/hybrid.md \"The fade\"); its errors are the faded model's.", nullable=True),
    ),
)

SELECTION = ArtifactSchema(
    name="selection", filename="selection.parquet", producer="sweep", sort_by=("heliostat_id",),
    description="Per heliostat the model used by aim and report: a fine candidate at the full "
                "training size (a hybrid ensemble, the GP correction, with `sweep "
                "--select-pretrained` the pre-trained network) where it beats fit-coarse's "
                "selected preset on the distance-weighted validation rows by the rule's margins "
                "(and is not worse forward in time), else that coarse model "
                "(docs/hybrid.md \"Selection\").",
    columns=(
        C("heliostat_id", "string", "", "Heliostat."),
        C("model", "string", "", "`hybrid`, `hybrid-octaves`, `gp` (the GP correction of the "
          "highest marginal likelihood), `gp-sun` (its sun-only structure), `pretrained-nn` or "
          "`coarse`."),
        C("preset", "string", "", "Coarse preset (of the coarse model under the hybrid)."),
        C("weight_decay", "float64", "", "Selected weight decay (NaN for coarse and "
          "pretrained-nn).", nullable=True),
        C("seed", "int64", "", "Seed of the selected member (0 for coarse)."),
        C("n_train", "int64", "", "Training rows."),
        C("val_error_mrad", "float64", "mrad", "Mean validation error of the selected model."),
        C("test_error_mrad", "float64", "mrad", "Mean test error of the selected model.", nullable=True),
        C("coarse_val_error_mrad", "float64", "mrad", "Mean validation error of the coarse "
          "model: fit-coarse's selected preset (the value of coarse_params.parquet)."),
        C("coarse_test_error_mrad", "float64", "mrad", "Mean test error of the coarse model "
          "(fit-coarse's, as coarse_params.parquet).", nullable=True),
        C("time_test_error_mrad", "float64", "mrad", "Forward in time: mean error on the time "
          "split's test rows of the selected model (the same model, weight decay and seed) "
          "trained again on the time split's training rows (missing: no time split, or a "
          "selected hybrid of a sweep without --time-split).", nullable=True),
        C("coarse_time_test_error_mrad", "float64", "mrad", "The same for the coarse model "
          "(fit-coarse's time-split fit, as coarse_params.parquet).", nullable=True),
        C("fade_length_deg", "float64", "deg", "Sun fade length of the selected fine model (inf: "
          "no fade; missing for the coarse model and pretrained-nn).", nullable=True),
        C("weighted_val_error_mrad", "float64", "mrad", "Mean validation error of the selected "
          "model with the validation rows weighted to the test rows' distances to training "
          "(what the rule compares; docs/hybrid.md \"Selection\")."),
        C("coarse_weighted_val_error_mrad", "float64", "mrad", "The same for the coarse model."),
        C("n_candidates", "int64", "", "Fine candidates compared (each fade length counted): "
          "the m of the rule's Bonferroni margin."),
        C("screen", "string", "", "The sweep's screen (docs/hybrid.md \"The screen\"): off "
          "(not run: every candidate trained), passed (the whole path trained) or failed (the "
          "path's first weight decays gained less than half the networks' margin: stopped)."),
        C("screen_gain", "float64", "", "The best relative gain of the screen's ensembles over "
          "the coarse model on the weighted validation rows (missing: not run).", nullable=True),
        C("forward_check", "string", "", "Forward-in-time check of a selected fine model (empty: "
          "the coarse model, or no time split): passed, failed (MODEL) (the static choice is "
          "selected instead), or not checked (a network without its time-split training: a sweep "
          "without --time-split). The rule's next choice stands in for a refused GP (a network "
          "always checked): 'failed (GP), then passed (MODEL)', or 'failed (GP), then failed "
          "(MODEL): fell back to the static choice'."),
        C("time_val_error_mrad", "float64", "mrad", "The forward check's figure: mean error on "
          "the time split's validation rows of the checked model trained on its training rows.",
          nullable=True),
        C("coarse_time_val_error_mrad", "float64", "mrad", "The same for the coarse model "
          "(fit-coarse's time-split fit).", nullable=True),
    ),
)

SELECTED_PREDICTIONS = ArtifactSchema(
    name="selected_predictions", filename="selected_predictions.parquet", producer="sweep",
    sort_by=COARSE_PREDICTIONS.sort_by, columns=COARSE_PREDICTIONS.columns,
    description="Per measurement the errors of the model selection.parquet chose (model = "
                "`selected`): the selected hybrid member, or the coarse model.")


PLAN = ArtifactSchema(
    name="plan", filename="plan.parquet", producer="plan", sort_by=("rank",),
    description="The measurement plan in the order of choice: each row the (heliostat, time, "
                "target) of the largest drop of its heliostat's expected year-round aim error "
                "given the rows before it, one heliostat on a target at a time (docs/plan.md). "
                "`plan.csv` beside it holds the same rows in time order for a plant scheduler.",
    columns=(
        C("rank", "int64", "", "Order of choice, 1 = the largest expected gain."),
        C("heliostat_id", "string", "", "Heliostat to measure."),
        C("time_utc", "timestamp", "UTC", "When to measure (the start of its slot; with "
          "--from-existing the time the chosen row was measured)."),
        C("day", "int64", "", "Solar day of the plan: 0 = --start (a day runs from local mean "
          "solar midnight)."),
        C("target", "string", "", "Calibration target, one the heliostat was measured on."),
        C("sun_azimuth_deg", "float64", "deg", "Sun azimuth at that time (NREL SPA), 0 = south, "
          "positive toward east."),
        C("sun_elevation_deg", "float64", "deg", "Apparent sun elevation at that time."),
        C("axis_1_steps", "float64", "steps", "Motor position of actuator 1 that puts the "
          "coarse model's beam on the target centre (the measured one with --from-existing)."),
        C("axis_2_steps", "float64", "steps", "The same for actuator 2."),
        C("expected_gain_mrad2", "float64", "mrad^2", "Reduction of the heliostat's expected "
          "year-round mean squared aim error by this row, after the heliostat's rows of lower "
          "rank."),
        C("expected_error_before_mrad", "float64", "mrad", "The heliostat's expected year-round "
          "RMS aim error from the parameters' uncertainty before this row (its rows so far and "
          "the plan's rows of lower rank)."),
        C("expected_error_after_mrad", "float64", "mrad", "The same after this row."),
        C("coarse_model", "string", "", "The coarse model whose covariance the gain rests on "
          "(fit-coarse's selected model; `nominal:<preset>` for a heliostat without a coarse "
          "fit: its nominal geometry with the field's most common preset)."),
        C("measurement_id", "string", "", "With --from-existing: the measurement chosen.",
          nullable=True),
    ),
)


def all_schemas() -> list[ArtifactSchema]:
    """Every artifact schema of heliocal, in the order of the stages that write them."""
    return [MEASUREMENTS, HELIOSTATS, REJECTED, SPLIT, COARSE_PARAMS, COARSE_PREDICTIONS,
            REGIMES, REGIME_PARAMS, ROLLING_ORIGIN, FIELD_PRIOR, HYBRID_PREDICTIONS, SWEEP,
            SELECTION, SELECTED_PREDICTIONS, PLAN]


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
