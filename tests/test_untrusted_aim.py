"""``aim`` and ``info`` on a fitted work directory (issue 32 findings 4-6, issue 31's aim items):
no internal error for anything a user can type, one reader per call, a swapped model refused, a
fixed point that does not converge reported, an aim far from the data warned about, and ``info``
that shows a modified artifact in its table instead of stopping.

The work directory is made once by the real stages on sample_data/juelich/paint (3 heliostats,
static-6, a 20-epoch one-network hybrid per heliostat): end-to-end, so the module is ``slow``.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

from heliocal.cli.main import app
from heliocal.pipeline.errors import FitError, SchemaError
from heliocal.pipeline.stages.aim import FAR_FROM_DATA_DAYS, aim_steps

pytestmark = pytest.mark.slow

PAINT = Path(__file__).resolve().parents[1] / "sample_data" / "juelich" / "paint"
TARGET = "solar_tower_juelich_lower"


def _run(runner, *args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def fitted(tmp_path_factory) -> Path:
    from typer.testing import CliRunner

    runner = CliRunner()
    wd = tmp_path_factory.mktemp("aim") / "wd"
    for args in (["ingest", PAINT], ["split-knn"], ["fit-coarse", "--preset", "static-6", "--rolling-origins", "0"],
                 ["fit-hybrid", "--max-epochs", "20", "--ensemble", "1"]):
        result = _run(runner, *args, "--workdir", wd, "--workers", "1", "--quiet") \
            if args[0].startswith("fit") else _run(runner, *args, "--workdir", wd, "--quiet")
        assert result.exit_code == 0, (args, result.stderr)
    return wd


@pytest.fixture
def wd(fitted, tmp_path) -> Path:
    return Path(shutil.copytree(fitted, tmp_path / "wd"))


def _aim(runner, wd, *extra, time="2023-06-21T12:00:00Z", target=TARGET):
    args = ["aim", "--workdir", wd, "--heliostat", "BE36", "--target", target]
    return _run(runner, *args, *(["--time", time] if time is not None else []), *extra)


# ------------------------------------------------------------------------------------------------
# what a user types
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("text", ["noon", "2023-02-30T12:00:00Z", "NaT", "", "99999-01-01"])
def test_a_time_that_is_not_one_is_a_usage_error(runner, fitted, text):
    """Before: `noon` and `2023-02-30T12:00:00Z` were internal DateParseErrors."""
    result = _aim(runner, fitted, time=text)
    assert result.exit_code == 2, result.stderr
    assert (f"Invalid value for '--time': {text!r} is not a UTC time such as "
            "2023-06-21T12:00:00Z") in result.stderr
    assert "internal error" not in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize("target", ["nan,nan,nan", "inf,0,0", "0,-inf,10"])
def test_a_target_that_is_not_finite_says_so(runner, fitted, target):
    """Before: `nan,nan,nan` said "not reachable"."""
    result = _aim(runner, fitted, target=target)
    assert result.exit_code == 2
    assert (f"Invalid value for '--target': {target!r}: the aim point must be three finite "
            "numbers E,N,U [m] (not finite), or a target name") in result.stderr


def test_an_unknown_env_input_is_refused_naming_the_known_ones(runner, fitted):
    """Before: `--env bogus=1` was silently ignored."""
    result = _aim(runner, fitted, "--env", "bogus=1")
    assert result.exit_code == 1
    assert result.stderr == (f"Error: unknown env input(s) ['bogus']: the env columns of "
                             f"{fitted}/measurements.parquet are none; give --env NAME=VALUE "
                             "with one of them\n")


@pytest.mark.parametrize("extra,option", [
    (["--env", "temperature"], "--env"), (["--env", "=1"], "--env"),
    (["--sun-azimuth", "nan", "--sun-elevation", "30"], "--sun-azimuth"),
    (["--sun-azimuth", "0", "--sun-elevation", "95"], "--sun-elevation"),
])
def test_malformed_env_and_sun_options_are_usage_errors(runner, fitted, extra, option):
    result = _aim(runner, fitted, *extra, time=None if "--sun-azimuth" in extra else
                  "2023-06-21T12:00:00Z")
    assert result.exit_code == 2 and f"Invalid value for '{option}'" in result.stderr


def test_times_with_an_offset_or_without_a_zone_are_read_as_utc(runner, fitted):
    out = [json.loads(_aim(runner, fitted, time=t).stdout)
           for t in ("2023-06-21T12:00:00Z", "2023-06-21T14:00:00+02:00", "2023-06-21T12:00:00")]
    assert len({(o["axis_1_steps"], o["axis_2_steps"], o["time_utc"]) for o in out}) == 1
    assert out[0]["time_utc"] == "2023-06-21 12:00:00+00:00"


def test_an_aim_far_past_the_data_is_answered_with_a_warning(runner, fitted):
    """Before: 2300-06-21 answered with steps and no word (a model extrapolated 277 years)."""
    import pyarrow.parquet as pq

    t = pq.read_table(fitted / "measurements.parquet").to_pandas()
    last = pd.to_datetime(t.loc[t["heliostat_id"] == "BE36", "timestamp"], utc=True).max()
    result = _aim(runner, fitted, time="2300-06-21T12:00:00Z")
    assert result.exit_code == 0, result.stderr
    out = json.loads(result.stdout)
    days = (pd.Timestamp("2300-06-21T12:00:00Z") - last) / pd.Timedelta(days=1)
    assert out["days_after_last_measurement"] == pytest.approx(days, abs=1e-6)
    assert out["warnings"] == [
        f"2300-06-21T12:00:00Z is {days:.0f} days after its last measurement ({last:%Y-%m-%d}): "
        f"the model of BE36 is extrapolated that far (more than {FAR_FROM_DATA_DAYS:g} days from "
        "its data); check the steps"]
    assert "extrapolated that far" in " ".join(result.stderr.split())
    near = json.loads(_aim(runner, fitted, time=f"{last + pd.Timedelta(days=30):%Y-%m-%dT%H:%M:%SZ}").stdout)
    assert near["warnings"] == [] and near["days_after_last_measurement"] == pytest.approx(30.0)


# ------------------------------------------------------------------------------------------------
# models and the fixed point
# ------------------------------------------------------------------------------------------------
def test_a_model_pair_copied_from_another_heliostat_is_refused(runner, wd):
    """Before: BF41's files under BE36's name (manifest updated) were used by aim."""
    folder = wd / "hybrid" / "hybrid"
    data = json.loads((wd / "fit-hybrid.manifest.json").read_text())
    for ext in ("json", "pt"):
        shutil.copy(folder / f"BF41.{ext}", folder / f"BE36.{ext}")
        raw = (folder / f"BE36.{ext}").read_bytes()
        data["files"][f"hybrid/hybrid/BE36.{ext}"].update(
            sha256=hashlib.sha256(raw).hexdigest(), size=len(raw))
    (wd / "fit-hybrid.manifest.json").write_text(json.dumps(data))
    result = _aim(runner, wd, "--model", "hybrid")
    assert result.exit_code == 1
    assert result.stderr == (
        f"Error: {folder / 'BE36.json'} is the model of heliostat 'BF41', not 'BE36' (its files "
        "were replaced by another heliostat's, and the manifest with them); rerun `heliocal "
        f"fit-hybrid --workdir {wd} --mode hybrid`, which writes BE36's model again\n")


def test_the_hybrids_fixed_point_converges_or_says_it_did_not(fitted):
    """Before: the loop stopped after max_iterations without a word and returned its last steps."""
    aim = dict(target=TARGET, time_utc="2023-06-21T12:00:00Z", model="hybrid")
    out = aim_steps(fitted, "BE36", **aim)
    assert 1 <= out["iterations"] < 50 and out["inverse_residual_mrad"] < 1e-6
    with pytest.raises(FitError, match=r"the hybrid model of BE36 did not converge to the aim "
                                       r"steps: after 1 fixed-point iterations the steps still "
                                       r"changed by [0-9.e+-]+ steps \(tolerance 1e-12\)"):
        aim_steps(fitted, "BE36", max_iterations=1, tolerance_steps=1e-12, **aim)


def test_one_aim_loads_each_manifest_once_and_reads_each_file_once(fitted, monkeypatch):
    """Before: one aim loaded the manifests 7 times and passed through the store 8 times."""
    from heliocal.pipeline.artifacts import manifests

    loads, opens = [], []
    real_load, real_open = manifests.load_manifest, manifests._open_committed
    monkeypatch.setattr(manifests, "load_manifest",
                        lambda r, s: loads.append(s) or real_load(r, s))
    monkeypatch.setattr(manifests, "_open_committed",
                        lambda m, rel: opens.append(rel) or real_open(m, rel))
    aim_steps(fitted, "BE36", target=TARGET, time_utc="2023-06-21T12:00:00Z")
    assert sorted(loads) == sorted(set(loads)), loads
    assert set(loads) <= {"ingest", "split-knn", "fit-coarse", "fit-hybrid", "sweep"}
    assert sorted(opens) == sorted(set(opens)), opens
    assert "hybrid/hybrid/BE36.pt" in opens and "coarse_params.parquet" in opens


# ------------------------------------------------------------------------------------------------
# info on a damaged work directory
# ------------------------------------------------------------------------------------------------
def test_info_shows_a_modified_artifact_in_its_table(runner, wd):
    """Before: `info DIR` exited 1 with the error of the modified file alone."""
    path = wd / "coarse_params.parquet"
    data = bytearray(path.read_bytes())
    data[100] ^= 0xFF
    path.write_bytes(bytes(data))
    result = _run(runner, "info", wd, "--json")
    assert result.exit_code == 0, result.stderr
    d = json.loads(result.stdout)
    status = {Path(a["path"]).name: a["status"] for a in d["artifacts"]}
    assert status["coarse_params.parquet"] == "modified"
    assert status["measurements.parquet"] == "fresh"
    assert d["aim_models"] == [] and "coarse_params.parquet was changed after" in d["aim_models_error"]
    text = _run(runner, "info", wd)
    assert text.exit_code == 0
    assert "the models `aim --model auto` uses cannot be told:" in text.stdout


def test_info_flags_a_tampered_manifest_and_the_next_stage_keeps_outside_files(runner, wd):
    outside = wd.parent / "victim_dir"
    outside.mkdir()
    (outside / "keep.txt").write_text("precious\n")
    data = json.loads((wd / "split-knn.manifest.json").read_text())
    data["run_id"] = "x/../../victim_dir"
    (wd / "split-knn.manifest.json").write_text(json.dumps(data))
    (wd / ".txn-split-knn-x").mkdir()
    d = json.loads(_run(runner, "info", wd, "--json").stdout)
    assert [h["path"] for h in d["hostile"]] == [str(wd / "split-knn.manifest.json")]
    assert "split-knn" not in [r["stage"] for r in d["runs"]]
    result = _run(runner, "split-knn", "--workdir", wd, "--quiet")
    assert result.exit_code == 0, result.stderr
    assert (outside / "keep.txt").read_text() == "precious\n"
    assert not (wd / ".txn-split-knn-x").exists()


def test_info_names_a_spill_folder_and_the_next_stage_removes_it(runner, wd):
    spill = wd / ".ingest-spill-abc123"
    spill.mkdir()
    (spill / "rejected-000000.parquet").write_bytes(b"half")
    d = json.loads(_run(runner, "info", wd, "--json").stdout)
    assert d["leftovers"] == [str(spill)]
    result = _run(runner, "split-knn", "--workdir", wd)
    assert result.exit_code == 0 and not spill.exists()
    assert ".ingest-spill-abc123 (a folder left by a killed run)" in " ".join(result.stderr.split())


def test_a_modified_model_is_refused_by_aim_in_one_line(runner, wd):
    pt = wd / "hybrid" / "hybrid" / "BE36.pt"
    pt.write_bytes(pt.read_bytes()[:-10])
    with pytest.raises(SchemaError, match="BE36.pt was changed after `heliocal fit-hybrid`"):
        aim_steps(wd, "BE36", target=TARGET, time_utc="2023-06-21T12:00:00Z", model="hybrid")
