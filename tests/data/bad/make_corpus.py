"""Write the small valid fixtures (tests/data/good/) and the bad-input corpus (tests/data/bad/).

Run once from the repository root and commit the output; the tests read the committed files and
never run this script:

    python tests/data/bad/make_corpus.py [--source ../shared/data/juelich]

The good fixtures are short extracts of the real Jülich data (PAINT, credited in its README) plus
a hand-written ENU log; every bad case is one of those fixtures with one kind of damage. The
expected outcome of each case is listed in tests/data/bad/CASES.md and in CASES of
tests/test_bad_inputs.py.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import random
import shutil
from pathlib import Path

HERE = Path(__file__).resolve().parent
GOOD = HERE.parent / "good"
BAD = HERE
REPO = HERE.parents[2]

# Rows of the Jülich log used for the small WGS84 fixture: the first 5 of AA31 and of AB27.
LOG_HELIOSTATS = {"AA31": 5, "AB27": 5}
PAINT_IDS = ("118671", "118750", "118826")  # BE36's first three calibrations


def _read_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def _csv_text(header, rows, delimiter=",", lineterminator="\n") -> str:
    buf = io.StringIO()
    w = csv.writer(buf, delimiter=delimiter, lineterminator=lineterminator)
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def write_good(source: Path) -> None:
    GOOD.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(source / "tower-measurements.json", GOOD / "tower-measurements.json")
    header, rows = _read_rows(source / "csv" / "juelich_calibration_log.csv")
    picked, left = [], dict(LOG_HELIOSTATS)
    for r in rows:
        if left.get(r[0], 0) > 0:
            picked.append(r)
            left[r[0]] -= 1
    (GOOD / "juelich_log_small.csv").write_text(_csv_text(header, picked), encoding="utf-8")

    # PAINT: BE36 with three calibrations; 118750 loses its UTIS spot, 118826 its HeliOS spot,
    # so --focal-spot falls back to the other detector for one row each.
    paint = GOOD / "paint_small"
    calib = paint / "BE36" / "calibration"
    calib.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(source / "paint" / "BE36" / "BE36-heliostat-properties.json",
                    paint / "BE36" / "BE36-heliostat-properties.json")
    stamps = json.loads((source / "paint" / "timestamps.json").read_text())
    for mid in PAINT_IDS:
        data = json.loads((source / "paint" / "BE36" / "calibration" /
                           f"{mid}-calibration-properties.json").read_text())
        if mid == "118750":
            del data["focal_spot"]["UTIS"]
        if mid == "118826":
            del data["focal_spot"]["HeliOS"]
        (calib / f"{mid}-calibration-properties.json").write_text(json.dumps(data), encoding="utf-8")
    (paint / "timestamps.json").write_text(json.dumps(
        {f"BE36_{m}": stamps[f"BE36_{m}"] for m in PAINT_IDS}, indent=1), encoding="utf-8")

    # A hand-written ENU log of two az-el heliostats with ideal actuators (values made up but
    # consistent: sun above the horizon, steps inside [0, 80000], spots within 0.5 m of T1).
    (GOOD / "enu_properties.toml").write_text('''\
[heliostats.H01]
heliostat_e_m = 10.0
heliostat_n_m = 30.0
heliostat_u_m = 1.5
axis_1_min_steps = 0
axis_1_max_steps = 80000
axis_2_min_steps = 0
axis_2_max_steps = 80000
axis_1_gear_ratio_steps_per_rad = 12000.0
axis_2_gear_ratio_steps_per_rad = 12000.0
axis_1_angle_offset_rad = -1.5
axis_2_angle_offset_rad = 0.0

[heliostats.H02]
heliostat_e_m = -15.0
heliostat_n_m = 40.0
heliostat_u_m = 1.5
axis_1_min_steps = 0
axis_1_max_steps = 80000
axis_2_min_steps = 0
axis_2_max_steps = 80000
axis_1_gear_ratio_steps_per_rad = 12000.0
axis_2_gear_ratio_steps_per_rad = 12000.0
axis_1_angle_offset_rad = -1.5
axis_2_angle_offset_rad = 0.0

[targets.T1]
center_enu_m = [0.0, 0.0, 30.0]
normal_enu = [0.0, 1.0, 0.0]
''', encoding="utf-8")
    enu_header = ["heliostat_id", "measurement_id", "sun_azimuth_deg", "sun_elevation_deg",
                  "axis_1_steps", "axis_2_steps", "target_name", "focal_spot_e_m",
                  "focal_spot_n_m", "focal_spot_u_m"]
    enu_rows = [
        ["H01", "1", "20.0", "45.0", "21000", "34000", "T1", "0.10", "0.00", "30.20"],
        ["H01", "2", "35.5", "50.2", "22500", "35100", "T1", "-0.21", "0.00", "29.85"],
        ["H01", "3", "-10.0", "55.0", "18800", "36050", "T1", "0.05", "0.00", "30.31"],
        ["H02", "1", "20.0", "45.0", "16400", "33900", "T1", "0.33", "0.00", "30.02"],
        ["H02", "2", "-30.0", "40.0", "14050", "33010", "T1", "-0.12", "0.00", "29.70"],
    ]
    (GOOD / "enu_log.csv").write_text(_csv_text(enu_header, enu_rows), encoding="utf-8")
    # The same without sun angles but with UTC timestamps: ingest computes them with SPA.
    ts_header = ["heliostat_id", "measurement_id", "timestamp"] + enu_header[4:]
    stamps_utc = ["2022-06-12T09:00:00Z", "2022-06-12T11:30:00Z", "2022-06-12T13:27:37Z",
                  "2022-06-12T10:00:00Z", "2022-06-12T15:00:00Z"]
    ts_rows = [[r[0], r[1], t] + r[4:] for r, t in zip(enu_rows, stamps_utc)]
    (GOOD / "enu_log_timestamps.csv").write_text(_csv_text(ts_header, ts_rows), encoding="utf-8")


def _edit(rows, row, col, value, header):
    rows = [list(r) for r in rows]
    rows[row][header.index(col)] = value
    return rows


#: Data row (0-based) -> heliostat id of hostile_heliostat_ids.csv: ids that would leave the
#: folder they name a file in, be hidden, be read as an option or be too long are rejected
#: (invalid_heliostat_id); row 6's odd but valid id is kept.
HOSTILE_IDS = {1: "../../../tmp/x/pwned", 2: "<img src=x onerror=alert(1)>", 3: ".hidden",
               4: "H" * 65, 6: "AB27.v2_-x", 7: "AB27/../AA31", 8: "-rf", 9: "AB 27"}


def _hostile_ids(rows, header):
    rows = [list(r) for r in rows]
    for i, hid in HOSTILE_IDS.items():
        rows[i][header.index("heliostat_id")] = hid
    return rows


def write_bad(source: Path) -> None:
    for p in BAD.iterdir():
        if p.name not in ("make_corpus.py", "CASES.md"):
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    shutil.copyfile(GOOD / "tower-measurements.json", BAD / "tower-measurements.json")
    header, rows = _read_rows(GOOD / "juelich_log_small.csv")
    H = header

    def put(name: str, text: str | bytes) -> None:
        path = BAD / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(text, bytes):
            path.write_bytes(text)
        else:
            path.write_text(text, encoding="utf-8")

    def log(name, rws, hdr=None, **kw):
        put(name, _csv_text(hdr or H, rws, **kw))

    good_text = _csv_text(H, rows)
    rng = random.Random(20240611)

    # --- file-level errors ---------------------------------------------------------------------
    put("empty.csv", b"")
    put("whitespace_only.csv", "\n   \n\t\n")
    log("header_only.csv", [])
    put("binary_garbage.csv", bytes(rng.randrange(256) for _ in range(2048)) + b"\0")
    put("not_utf8.csv", _csv_text(H, _edit(rows, 2, "target_name", "solar_tower_jülich_lower", H))
        .encode("latin-1"))
    log("semicolon_delimiter.csv", rows, delimiter=";")
    i = H.index("axis_1_motor_position")
    log("missing_column_axis_1.csv", [r[:i] + r[i + 1:] for r in rows], H[:i] + H[i + 1:])
    i = H.index("sun_elevation")
    log("duplicated_column.csv", [r + [r[i]] for r in rows], H + ["sun_elevation"])
    extra = [list(r) for r in rows]
    extra[2] = extra[2] + ["surplus"]
    log("extra_field_in_row.csv", extra)
    lines = good_text.splitlines(keepends=True)
    put("unterminated_quote.csv", "".join(lines[:3]) + lines[3].replace("AA31", '"AA31', 1)
        + "".join(lines[4:]))
    t = H.index("timestamp")
    log("timestamps_without_zone.csv", [r[:t] + [r[t].rstrip("Z")] + r[t + 1:] for r in rows])
    a = H.index("sun_azimuth")
    log("azimuth_north_clockwise.csv",
        [r[:a] + [repr(180.0 - float(r[a]))] + r[a + 1:] for r in rows])
    put("unknown_file_type.xlsx", good_text)
    put("parquet_garbage.parquet", good_text)
    low = [list(r) for r in rows]
    for r in low:
        r[H.index("sun_elevation")] = "-5.0"
    log("all_rows_rejected.csv", low)
    shutil.copyfile(GOOD / "enu_log.csv", BAD / "enu_log.csv")
    enu_h, enu_rows = _read_rows(GOOD / "enu_log.csv")
    log("enu_log_without_sun.csv", [r[:2] + r[4:] for r in enu_rows], enu_h[:2] + enu_h[4:])
    props = (GOOD / "enu_properties.toml").read_text()
    put("properties_malformed.toml", props.replace("heliostat_e_m = 10.0", "heliostat_e_m = = 10.0"))
    put("properties_lacks_max_steps.toml", props.replace("axis_1_max_steps = 80000\n", "", 1))
    put("tower_malformed.json", (GOOD / "tower-measurements.json").read_text()[:700])
    # PAINT folder whose heliostat-properties file lacks its kinematics
    pb = BAD / "paint_bad_properties" / "BE36"
    shutil.copytree(GOOD / "paint_small" / "BE36" / "calibration", pb / "calibration")
    shutil.copyfile(GOOD / "paint_small" / "timestamps.json", pb.parent / "timestamps.json")
    hp = json.loads((GOOD / "paint_small" / "BE36" / "BE36-heliostat-properties.json").read_text())
    del hp["kinematics_properties"]
    put("paint_bad_properties/BE36/BE36-heliostat-properties.json", json.dumps(hp))

    # --- row-level problems: quarantined, the other rows kept ------------------------------------
    r = _edit(rows, 1, "axis_1_motor_position", "abc", H)
    log("wrong_types.csv", _edit(r, 4, "sun_elevation", "high", H))
    r = _edit(rows, 0, "axis_2_motor_position", "NaN", H)
    r = _edit(r, 2, "focal_spot_alt", "inf", H)
    log("nan_inf.csv", _edit(r, 3, "sun_azimuth", "-Infinity", H))
    log("huge_number.csv", _edit(rows, 6, "focal_spot_alt", "1e400", H))
    log("negative_steps.csv", _edit(rows, 1, "axis_1_motor_position", "-500", H))
    log("huge_steps.csv", _edit(rows, 5, "axis_2_motor_position", "1000000000000", H))
    r = _edit(rows, 2, "timestamp", "2022-13-45T99:00:00Z", H)
    log("timestamp_unparsable.csv", _edit(r, 3, "timestamp", "yesterday noon", H))
    log("timestamp_one_without_zone.csv", _edit(rows, 7, "timestamp", rows[7][t].rstrip("Z"), H))
    # timestamps outside the plausible range (1990 .. now + 1 day); one valid with nanoseconds,
    # whose unit pandas would otherwise extend to the years outside 1677-2262
    r = _edit(rows, 0, "timestamp", "1700-06-03T09:20:02Z", H)
    r = _edit(r, 2, "timestamp", "2300-06-03T09:38:50Z", H)
    r = _edit(r, 4, "timestamp", "9999-12-31T23:59:59Z", H)
    log("timestamps_implausible.csv",
        _edit(r, 5, "timestamp", rows[5][t].replace("Z", ".123456789Z"), H))

    def day_month(stamp: str) -> str:  # 2022-06-03T09:20:02Z -> 03.06.2022 09:20:02Z
        date, clock = stamp.rstrip("Z").split("T")
        y, m, d = date.split("-")
        return f"{d}.{m}.{y} {clock}Z"

    log("timestamp_day_month.csv", _edit(rows, 3, "timestamp", day_month(rows[3][t]), H))
    log("timestamps_day_month.csv", [r[:t] + [day_month(r[t])] + r[t + 1:] for r in rows])
    log("sun_below_horizon.csv", _edit(rows, 1, "sun_elevation", "-3.2", H))
    log("sun_elevation_out_of_range.csv", _edit(rows, 8, "sun_elevation", "123.0", H))
    lat = H.index("focal_spot_lat")
    log("focal_spot_kilometres_away.csv",
        _edit(rows, 4, "focal_spot_lat", repr(float(rows[4][lat]) + 0.01), H))
    log("focal_spot_latitude_invalid.csv", _edit(rows, 3, "focal_spot_lat", "95.0", H))
    s = H.index("sample_id")
    log("duplicated_measurement_id.csv", _edit(rows, 3, "sample_id", rows[2][s], H))
    r = [list(x) for x in rows]
    for x in r[5:7]:
        x[0] = "ZZ99"
        for c in ("heliostat_lat", "heliostat_lon", "heliostat_alt"):
            x[H.index(c)] = ""
    log("unknown_heliostat.csv", r)
    log("hostile_heliostat_ids.csv", _hostile_ids(rows, H))
    r = _edit(rows, 6, "target_name", "moon_target", H)
    for c in ("target_center_lat", "target_center_lon", "target_center_alt"):
        r = _edit(r, 6, c, "", H)
    log("unknown_target.csv", r)
    r = _edit(rows, 0, "axis_1_motor_position", "", H)
    r = _edit(r, 1, "target_name", "", H)
    log("missing_values.csv", _edit(r, 2, "heliostat_id", "", H))
    cut = lines[-1][: lines[-1].index(rows[-1][H.index("target_name")])]
    put("truncated_last_line.csv", "".join(lines[:-1]) + cut.rstrip(",") + "\n")
    r = _edit(rows, 9, "target_name", "solar_tower_juelich_lower, spare", H)
    log("quoted_comma_in_target.csv", r)
    log("sun_angles_empty.csv", _edit(_edit(rows, 0, "sun_azimuth", "", H), 0, "sun_elevation", "", H))
    # cases that must be read in full (nothing rejected)
    extra_h, extra_rows = _read_rows(source / "csv" / "juelich_calibration_log.csv")
    single = next(x for x in extra_rows if x[0] == "AC32")
    log("heliostat_with_one_measurement.csv", rows + [single])
    put("crlf_bom.csv", "\ufeff" + _csv_text(H, rows, lineterminator="\r\n"))
    put("blank_lines.csv", "".join(lines[:3]) + "\n  \n" + "".join(lines[3:]) + "\n\n")
    r = [list(x) + [""] for x in rows]
    log("trailing_commas.csv", r)
    log("enu_unknown_heliostat.csv", enu_rows + [["H03", "1", "20.0", "45.0", "21000", "34000",
                                                   "T1", "0.10", "0.00", "30.20"]], enu_h)

    # PAINT folder with mixed valid and broken calibration files
    pm = BAD / "paint_mixed"
    shutil.copytree(GOOD / "paint_small" / "BE36", pm / "BE36")
    shutil.copyfile(GOOD / "paint_small" / "timestamps.json", pm / "timestamps.json")
    c = pm / "BE36" / "calibration"
    good_json = (c / "118671-calibration-properties.json").read_text()
    put("paint_mixed/BE36/calibration/200001-calibration-properties.json", good_json[:-40])
    put("paint_mixed/BE36/calibration/200002-calibration-properties.json", "[1, 2, 3]")
    put("paint_mixed/BE36/calibration/200003-calibration-properties.json", b"\xff\xfe{\x00")
    put("paint_mixed/BE36/calibration/notes.json", "{}")
    put("paint_mixed/ZZ99/calibration/300001-calibration-properties.json", good_json)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=REPO.parent / "shared" / "data" / "juelich")
    args = parser.parse_args()
    write_good(args.source)
    write_bad(args.source)


if __name__ == "__main__":
    main()
