"""Input folders are untrusted too (issue 32, finding 3): a link in a PAINT folder that leads
outside it, a FIFO named like a calibration file, a work directory inside the source folder and
heliostat ids Windows reserves. Each case runs ``heliocal ingest`` on a copy of
``tests/data/good/paint_small`` (BE36, 3 measurements) or on a three-line log; the expected
outcome is written out per case.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from heliocal.cli.main import app
from heliocal.pipeline.artifacts.schemas import heliostat_id_problem, suggest_heliostat_id

GOOD = Path(__file__).resolve().parent / "data" / "good"
PAINT_SMALL = GOOD / "paint_small"


def _paint(tmp_path: Path) -> Path:
    paint = Path(shutil.copytree(PAINT_SMALL, tmp_path / "paint"))
    shutil.copy(GOOD / "tower-measurements.json", tmp_path)
    return paint


def _ingest(runner, *args):
    return runner.invoke(app, ["ingest", *map(str, args), "--quiet"])


def _one_line(result) -> str:
    assert result.exit_code == 1, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr and "internal error" not in result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr
    return result.stderr


def _rejected(wd: Path):
    return pq.read_table(wd / "rejected.parquet").to_pandas()


def test_a_calibration_file_linked_outside_is_rejected_without_its_bytes(runner, tmp_path):
    """Before: ingested silently, the outside file's bytes copied into rejected.parquet's raw."""
    paint = _paint(tmp_path)
    secret = tmp_path / "secret.txt"
    secret.write_text("secret-outside-bytes")
    (paint / "BE36" / "calibration" / "99999-calibration-properties.json").symlink_to(secret)
    result = _ingest(runner, paint, "--workdir", tmp_path / "wd")
    assert result.exit_code == 0, result.stderr
    rej = _rejected(tmp_path / "wd")
    row = rej[rej["measurement_id"] == "99999"].iloc[0]
    assert row["reason"] == "malformed_file"
    assert row["detail"].startswith(f"a symbolic link to {secret}, outside the PAINT folder")
    assert row["raw"] == "" and not rej["raw"].str.contains("secret-outside").any()


def test_a_link_inside_the_paint_folder_is_read_like_a_copy(runner, tmp_path):
    paint = _paint(tmp_path)
    cal = paint / "BE36" / "calibration"
    (cal / "99997-calibration-properties.json").symlink_to(cal / "118671-calibration-properties.json")
    result = _ingest(runner, paint, "--workdir", tmp_path / "wd")
    assert result.exit_code == 0, result.stderr
    ids = set(pq.read_table(tmp_path / "wd" / "measurements.parquet")["measurement_id"].to_pylist())
    assert "99997" in ids  # kept (it has no timestamp, which measurements allow)


def test_a_fifo_named_like_a_calibration_file_is_rejected_without_blocking(runner, tmp_path):
    """Before: ingest hung forever reading it."""
    paint = _paint(tmp_path)
    os.mkfifo(paint / "BE36" / "calibration" / "99998-calibration-properties.json")
    t0 = time.monotonic()
    result = _ingest(runner, paint, "--workdir", tmp_path / "wd")
    assert result.exit_code == 0 and time.monotonic() - t0 < 30, result.stderr
    row = _rejected(tmp_path / "wd").query("measurement_id == '99998'").iloc[0]
    assert (row["reason"], row["detail"]) == (
        "malformed_file", "a FIFO (named pipe), not a file; heliocal reads only regular files")


def test_a_properties_file_linked_outside_is_refused_in_one_line(runner, tmp_path):
    paint = _paint(tmp_path)
    prop = paint / "BE36" / "BE36-heliostat-properties.json"
    outside = tmp_path / "elsewhere.json"
    shutil.move(prop, outside)
    prop.symlink_to(outside)
    line = _one_line(_ingest(runner, paint, "--workdir", tmp_path / "wd"))
    assert line.startswith(f"Error: {prop}: a symbolic link to {outside}, outside the PAINT folder")


@pytest.mark.parametrize("inside", ["run", "."])
def test_a_work_directory_inside_the_source_folder_is_refused(runner, tmp_path, inside):
    """Before: "changed while heliocal ingest was reading it" on every run."""
    paint = _paint(tmp_path)
    wd = paint / inside
    line = _one_line(_ingest(runner, paint, "--workdir", wd))
    assert line == (f"Error: the work directory {wd} is inside the source folder {paint}: ingest "
                    f"would read the files it writes there; use a --workdir outside {paint}\n")
    assert sorted(p.name for p in paint.iterdir()) == ["BE36", "timestamps.json"]


def test_a_source_folder_inside_the_work_directory_is_fine(runner, tmp_path):
    wd = tmp_path / "wd"
    paint = Path(shutil.copytree(PAINT_SMALL, wd / "paint"))
    shutil.copy(GOOD / "tower-measurements.json", wd)
    assert _ingest(runner, paint, "--workdir", wd).exit_code == 0


def test_a_fifo_given_as_the_log_is_refused_without_blocking(runner, tmp_path):
    os.mkfifo(tmp_path / "log.csv")
    line = _one_line(_ingest(runner, tmp_path / "log.csv", "--workdir", tmp_path / "wd"))
    assert "is a FIFO (named pipe), not a file or folder; save the log to a file" in line


# ------------------------------------------------------------------------------------------------
# heliostat ids Windows reserves
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("hid,stem,suggestion", [
    ("CON", "CON", "CON_"), ("NUL.txt", "NUL", "NUL_.txt"), ("com1", "com1", "com1_"),
    ("Aux", "Aux", "Aux_"), ("LPT9.a.b", "LPT9", "LPT9_.a.b"), ("prn", "prn", "prn_"),
])
def test_windows_device_names_are_invalid_ids_with_a_suggestion(hid, stem, suggestion):
    """Before: CON and NUL.txt were accepted although the id rule is meant to be portable."""
    assert heliostat_id_problem(hid) == (
        f"{stem!r} is a device name Windows reserves (CON, PRN, AUX, NUL, COM1-9, LPT1-9), so no "
        "file can have that name there")
    assert suggest_heliostat_id(hid) == suggestion
    assert heliostat_id_problem(suggestion) is None


@pytest.mark.parametrize("hid", ["CONSOLE", "COM10", "LPT0", "NULL", "CON_", "ACON", "BE36"])
def test_names_that_only_look_like_device_names_stay_valid(hid):
    assert heliostat_id_problem(hid) is None


def test_ingest_rejects_device_names_and_keeps_the_rest(runner, tmp_path):
    log = GOOD / "juelich_log_small.csv"
    text = log.read_text().splitlines()
    header, rows = text[0], text[1:]
    col = header.split(",").index("heliostat_id")
    ids = ["CON", "NUL.txt", "BE36"]
    out = [header]
    for k, row in enumerate(rows):
        cells = row.split(",")
        cells[col] = ids[k % len(ids)]
        out.append(",".join(cells))
    (tmp_path / "log.csv").write_text("\n".join(out) + "\n")
    shutil.copy(GOOD / "tower-measurements.json", tmp_path)
    result = _ingest(runner, tmp_path / "log.csv", "--workdir", tmp_path / "wd")
    assert result.exit_code == 0, result.stderr
    rej = _rejected(tmp_path / "wd").query("reason == 'invalid_heliostat_id'")
    assert sorted(set(rej["heliostat_id"])) == ["CON", "NUL.txt"]
    assert "e.g. 'NUL_.txt'" in rej.loc[rej["heliostat_id"] == "NUL.txt", "detail"].iloc[0]
    kept = set(pq.read_table(tmp_path / "wd" / "measurements.parquet")["heliostat_id"].to_pylist())
    assert kept == {"BE36"}



def test_simulate_overwrite_never_removes_through_a_planted_link(tmp_path):
    """`simulate --overwrite` removes the previous simulation's files: through a link `paint/`
    to a real PAINT download it removed that download's calibration files. Refused, one line."""
    from heliocal.pipeline.errors import UnsafePathError
    from heliocal.pipeline.models.simulator import simulate_field
    from heliocal.pipeline.stages.simulate import write_field

    download = Path(shutil.copytree(PAINT_SMALL, tmp_path / "download"))
    out = tmp_path / "sim"
    out.mkdir()
    (out / "paint").symlink_to(download)
    field = simulate_field(1, seed=3, measurements=(20, 20), dynamic_fraction=0.0)
    with pytest.raises(UnsafePathError, match=r"sim/paint is a symbolic link to .*download"):
        write_field(field, out, overwrite=True)
    assert len(list((download / "BE36" / "calibration").iterdir())) == 3
