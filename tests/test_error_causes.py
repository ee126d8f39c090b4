"""Errors name their real cause (issue 31): a full disk or an exhausted memory while ingest
spills a Parquet log is not "not a readable Parquet file"; a local time that does not exist in
its time zone is not "not a UTC time"; a malformed ground_truth.json is said, not skipped
silently; standard errors from a pseudo-inverse are flagged."""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from heliocal.cli.main import app
from heliocal.pipeline.io.spill import SortedSpill

ROOT = Path(__file__).resolve().parents[1]
SYNTHETIC_LOG = ROOT / "sample_data" / "synthetic" / "calibration_log.csv"


@pytest.fixture
def parquet_log(tmp_path) -> Path:
    """The synthetic sample's calibration log (600 rows) as a Parquet file."""
    log = tmp_path / "calibration_log.parquet"
    pd.read_csv(SYNTHETIC_LOG).to_parquet(log, index=False)
    return log


def _ingest(log: Path, workdir: Path, *args: str):
    return CliRunner().invoke(app, ["ingest", str(log), "--workdir", str(workdir), "--quiet",
                                    *args])


def test_a_full_disk_while_spilling_a_parquet_log_is_reported_as_a_full_disk(parquet_log,
                                                                               tmp_path,
                                                                               monkeypatch):
    """The log is read in batches of 100 rows and spilled, sorted, to the work directory; the
    disk fills on the first spill. Expected: the resource line of pipeline/errors.py for ENOSPC
    (what to do: free space or another --workdir), not the Parquet reader's 'export the log
    again', which sends the user after a file that is fine."""
    def full_disk(self, table):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "wd" / "run.parquet"))

    monkeypatch.setattr(SortedSpill, "add", full_disk)
    result = _ingest(parquet_log, tmp_path / "wd", "--batch-rows", "100")
    assert result.exit_code == 1
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"Error: {tmp_path / 'wd' / 'run.parquet'}: no space left on the device (ENOSPC); free "
        "space on that disk or use another --workdir"), lines
    assert "Parquet" not in lines[0]


def test_running_out_of_memory_while_reading_a_parquet_log_says_so(parquet_log, tmp_path,
                                                                   monkeypatch):
    """A MemoryError while a batch is spilled is neither an unreadable file nor a bug in
    heliocal: one line naming the log, the batch size and the fix (a smaller --batch-rows)."""
    def no_memory(self, table):
        raise MemoryError()

    monkeypatch.setattr(SortedSpill, "add", no_memory)
    result = _ingest(parquet_log, tmp_path / "wd", "--batch-rows", "100")
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [
        f"Error: {parquet_log}: out of memory while reading the log in batches of 100 rows; "
        "give a smaller --batch-rows or free memory, then rerun the command"]


def test_a_damaged_parquet_log_is_still_reported_as_unreadable(tmp_path):
    """The reader's own errors keep their message (the file, 'not a readable Parquet file')."""
    log = tmp_path / "calibration_log.parquet"
    log.write_bytes(b"PAR1" + b"\0" * 64)
    result = _ingest(log, tmp_path / "wd")
    assert result.exit_code == 1
    assert result.stderr.startswith(f"Error: {log}: not a readable Parquet file (")


def test_a_local_time_that_does_not_exist_or_occurs_twice_says_so(tmp_path):
    """The synthetic log with naive local times and --timezone Europe/Berlin: 2023-03-26 02:30
    does not exist there (the clocks jump from 02:00 to 03:00 CET -> CEST) and 2023-10-29 02:30
    occurs twice (03:00 CEST -> 02:00 CET). Each is rejected as unparsable_timestamp with that
    reason, not 'is not a UTC time' (it is a local time, and the user asked for one); every other
    row is the same instant as in the UTC log and is kept."""
    log = pd.read_csv(SYNTHETIC_LOG)
    local = pd.to_datetime(log["timestamp"]).dt.tz_convert("Europe/Berlin")
    log["timestamp"] = local.dt.strftime("%Y-%m-%d %H:%M:%S")
    log.loc[0, "timestamp"] = "2023-03-26 02:30:00"
    log.loc[1, "timestamp"] = "2023-10-29 02:30:00"
    path = tmp_path / "local_log.csv"
    log.to_csv(path, index=False)
    result = _ingest(path, tmp_path / "wd", "--timezone", "Europe/Berlin", "--tower",
                     str(SYNTHETIC_LOG.parent / "tower-measurements.json"))
    assert result.exit_code == 0, result.stderr
    rejected = pd.read_parquet(tmp_path / "wd" / "rejected.parquet")
    by_id = rejected.set_index("measurement_id")
    ids = log["sample_id"].astype(str)
    assert by_id.loc[ids[0], "reason"] == "unparsable_timestamp"
    assert by_id.loc[ids[0], "detail"] == (
        "timestamp '2023-03-26 02:30:00' does not exist in time zone Europe/Berlin (a clock "
        "change skips it); write it with its UTC offset, e.g. 2024-06-01T12:00:00+02:00")
    assert by_id.loc[ids[1], "reason"] == "unparsable_timestamp"
    assert by_id.loc[ids[1], "detail"] == (
        "timestamp '2023-10-29 02:30:00' occurs twice in time zone Europe/Berlin (a clock "
        "change repeats it); write it with its UTC offset, e.g. 2024-06-01T12:00:00+02:00")
    assert not rejected["detail"].str.contains("not a UTC time").any()
    kept = pd.read_parquet(tmp_path / "wd" / "measurements.parquet").set_index("measurement_id")
    assert len(kept) + len(rejected) == len(log)
    utc = pd.to_datetime(pd.read_csv(SYNTHETIC_LOG)["timestamp"]).set_axis(ids)
    assert (kept["timestamp"] == utc.loc[kept.index]).all()


def test_an_unknown_time_zone_is_an_option_error(tmp_path):
    """A --timezone that is no IANA zone is one line about the option, not every row rejected as
    an unreadable time."""
    result = _ingest(SYNTHETIC_LOG, tmp_path / "wd", "--timezone", "Europe/Atlantis")
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [
        "Error: The 'timezone' parameter of ingest must be an IANA time zone such as "
        "Europe/Berlin or UTC. Got 'Europe/Atlantis' instead."]


@pytest.mark.parametrize("content, problem", [
    ("{not json", "not valid JSON (Expecting property name enclosed in double quotes, line 1 "
                  "column 2)"),
    ('{"heliostats": [0.1, 0.2]}', "'heliostats' is not an object of heliostats"),
])
def test_a_malformed_ground_truth_is_said_once_and_recorded(tmp_path, caplog, content, problem):
    """A simulated field's ground_truth.json beside the ingested sources gives the report its
    measurement floor. A malformed one was skipped silently (the report then said 'unknown'
    as if there were no file). Now: one warning line naming the file and the problem, recorded
    in the summary (--json) and on the overview page, and still no floor."""
    import json
    import logging

    from heliocal.pipeline.stages import report as report_stage
    from test_report import make_workdir

    wd = make_workdir(tmp_path, "coarse")
    field = tmp_path / "field"
    field.mkdir()
    truth = field / "ground_truth.json"
    truth.write_text(content)
    manifest = wd / "ingest.manifest.json"
    m = json.loads(manifest.read_text())
    m.setdefault("options", {})["sources"] = [str(field / "calibration_log.csv")]
    manifest.write_text(json.dumps(m))
    caplog.set_level(logging.WARNING, logger="heliocal")
    summary = report_stage.run_report(wd, workers=1)
    said = f"{truth}: {problem}; the report has no measurement floor from it (give --floor-mrad)"
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings.count(said) == 1 and not [w for w in warnings if "ground_truth" in w
                                              and w != said]
    assert summary["measurement_floor"] == {"value_mrad": None, "source": "", "problems": [said]}
    assert said not in summary["notes"]   # printed once: the warning
    index = (wd / "report" / "index.html").read_text()
    assert "Measurement floor: unknown" in index and str(truth) in index


def test_fit_diagnostics_flags_standard_errors_from_a_pseudo_inverse():
    """A Jacobian whose second column is zero (a free parameter nothing moves, no prior row):
    J^T J is exactly singular, np.linalg.inv refuses it, and the standard errors come from the
    pseudo-inverse: flagged. Reference values by hand: J = [[2, 0], [0, 0], [0, 0], [1, 0]],
    unit prior sigmas, residuals r = (1, 1, 1, 1) on 4 data rows and 2 free parameters, so
    s^2 = 4 / 2 = 2; pinv(J^T J) = diag(1/5, 0): std = (sqrt(2/5), 0). A regular Jacobian
    (identity on 2 rows, residuals 0) gives no flag."""
    from heliocal.pipeline.models.fit_diagnostics import fit_diagnostics

    sigma = np.ones(28)
    free = np.array([0, 1])
    J = np.array([[2.0, 0.0], [0.0, 0.0], [0.0, 0.0], [1.0, 0.0]])
    d = fit_diagnostics(J, np.ones(4), 4, free, sigma)
    assert d.pseudo_inverse
    np.testing.assert_allclose(d.std_error[:2], [np.sqrt(2 / 5), 0.0], rtol=1e-12)
    assert not d.determined[1]
    assert d.flag_status("batched LM: converged") == (
        "batched LM: converged; standard errors from a pseudo-inverse of a singular J^T J: not "
        "trustworthy")
    regular = fit_diagnostics(np.eye(2), np.zeros(2), 2, free, sigma)
    assert not regular.pseudo_inverse and regular.flag_status("ok") == "ok"


@pytest.mark.parametrize("solver", ["scipy", "batched"])
def test_a_coarse_fit_whose_normal_matrix_cannot_be_inverted_says_so_in_its_status(solver,
                                                                                  monkeypatch):
    """Both solvers' fits carry the flag into their status (coarse_params.parquet fit_status)
    when the inverse of J^T J fails. A real fit's J^T J has the prior rows in it and is not
    exactly singular, so the inverse is made to fail here; the same fit without that has a plain
    status and the same fitted parameters (the flag changes no number)."""
    import torch

    from heliocal.pipeline.models import fit_diagnostics as diagnostics
    from heliocal.pipeline.models.coarse import (MeasurementBatch, fit_heliostat,
                                                 fit_heliostats_batched)
    from heliocal.pipeline.physics.parameters import HeliostatSpec, nominal_parameters
    from heliocal.pipeline.stages.ingest import ingest

    measurements, helio, _, _ = ingest([ROOT / "sample_data" / "juelich" / "paint"])
    row = helio.iloc[0]
    rows = measurements[measurements["heliostat_id"] == row["heliostat_id"]]
    spec, nominal = HeliostatSpec.from_row(row), nominal_parameters(row)
    data = MeasurementBatch.from_frame(rows)

    def fit():
        if solver == "scipy":
            return fit_heliostat(spec, nominal, data, "static-6", loss="soft_l1")
        return fit_heliostats_batched([spec], [nominal], [data], "static-6", loss="soft_l1")[0]

    plain = fit()
    real_inv = np.linalg.inv

    def singular(a, *args, **kw):
        if np.shape(a) == (6, 6):   # static-6's J^T J
            raise np.linalg.LinAlgError("Singular matrix")
        return real_inv(a, *args, **kw)

    monkeypatch.setattr(diagnostics.np.linalg, "inv", singular)
    flagged = fit()
    assert "pseudo-inverse" not in plain.status
    assert flagged.status == f"{plain.status}; standard errors from a pseudo-inverse of a " \
                             "singular J^T J: not trustworthy"
    assert torch.equal(flagged.params, plain.params)


def test_the_report_flags_standard_errors_from_a_pseudo_inverse(tmp_path):
    """A selected fit whose fit_status carries the pseudo-inverse flag gets a note beside its
    parameters, addressed to its heliostat (so its own page shows it too); the others none."""
    from heliocal.pipeline.report.inputs import load_inputs
    from heliocal.pipeline.report.metrics import compute_metrics
    from heliocal.pipeline.report.pages import build_report
    from heliocal.pipeline.vocabulary import STD_ERROR_PSEUDO_INVERSE
    from test_report import make_workdir

    inp = load_inputs(make_workdir(tmp_path, "coarse"))
    cp = inp.coarse_params
    hid = sorted(cp["heliostat_id"].unique())[0]
    cp["fit_status"] = cp["fit_status"].astype(str)
    cp.loc[cp["heliostat_id"] == hid, "fit_status"] += f"; {STD_ERROR_PSEUDO_INVERSE}"
    notes = [b for b in build_report(inp, compute_metrics(inp))
             if b[0] == "note" and STD_ERROR_PSEUDO_INVERSE in b[1]]
    assert notes == [("note", f"{hid}: {STD_ERROR_PSEUDO_INVERSE} (the data and the prior leave "
                              "a direction of the parameters free).", hid)]
