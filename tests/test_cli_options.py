"""Options and formats the CLI shares with the library, each defined once: the number format of
the result tables (cli/app.py fmt_number) and the checks of option values (the library's, which
the CLI passes on)."""

from __future__ import annotations

import math

import pytest
from typer.testing import CliRunner

from heliocal.cli.app import fmt_number
from heliocal.cli.main import app
from heliocal.pipeline.errors import HeliocalError, ParameterError


def test_fmt_number_rounds_to_the_given_decimals_and_marks_missing_values():
    """Expected strings written out by hand: three decimals by default (error tables in mrad),
    two for split-knn's distances in degrees; a missing value (None, NaN, as a summary carries
    one for a split without rows) prints as '-', never 'nan'."""
    assert fmt_number(1.23456) == "1.235"
    assert fmt_number(0.5, 2) == "0.50"
    assert fmt_number(-0.0004) == "-0.000"
    assert fmt_number(None) == "-"
    assert fmt_number(math.nan) == "-"
    assert fmt_number(float("nan"), 2) == "-"


BASELINES_ERROR = ("The 'baselines' parameter of sweep must list nn-only and/or pretrained-nn. "
                   "Got 'foo' instead.")


def test_sweep_baselines_are_checked_once_by_the_library_before_anything_runs(tmp_path):
    """`sweep --baselines` is checked by run_sweep alone (the CLI only splits the list): the
    command and the library give the same one line, before the work directory is created. The
    message is written out here, its spelling of the choices from the vocabulary."""
    from heliocal.pipeline.stages.sweep import run_sweep

    result = CliRunner().invoke(app, ["sweep", "--workdir", str(tmp_path / "wd"),
                                      "--baselines", "nn-only,foo", "--quiet"])
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [f"Error: {BASELINES_ERROR}"]
    with pytest.raises(ParameterError) as err:
        run_sweep(tmp_path / "wd2", baselines=("nn-only", "foo"))
    assert str(err.value) == BASELINES_ERROR
    assert not (tmp_path / "wd").exists() and not (tmp_path / "wd2").exists()


def test_cli_defaults_are_the_library_defaults(tmp_path, monkeypatch):
    """What `ingest` and `fit-hybrid` pass to the library when no option is given equals the
    library's own defaults (IngestOptions(), FineConfig()): both read them from one place, the
    vocabulary and FineConfig, instead of repeating literals. The stages are replaced by
    recorders; nothing runs."""
    import dataclasses

    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.models.config import FineConfig
    from heliocal.pipeline.stages import fit_hybrid, ingest

    seen = {}

    def recorder(name, value):
        seen[name] = value
        raise HeliocalError("recorded")   # stop here: the command prints it as its one line

    monkeypatch.setattr(ingest, "run_ingest",
                        lambda sources, workdir, opts, **kw: recorder("ingest", opts))
    monkeypatch.setattr(fit_hybrid, "run_fit_hybrid",
                        lambda workdir, **kw: recorder("hybrid", kw["config"]))
    runner = CliRunner()
    for args in (["ingest", str(tmp_path)], ["fit-hybrid"]):
        result = runner.invoke(app, [*args, "--workdir", str(tmp_path / "w"), "--quiet"])
        assert (result.exit_code, result.stderr) == (1, "Error: recorded\n")
    assert dataclasses.asdict(seen["ingest"]) == dataclasses.asdict(IngestOptions())
    assert seen["hybrid"] == FineConfig()


def test_ingest_lists_its_detector_and_azimuth_choices_from_the_vocabulary():
    """--focal-spot and --azimuth-convention are vocabulary choices (FocalSpotDetector,
    AzimuthConvention): --help lists exactly their spellings, and the library refuses any other
    with its one line (tests/test_ingest.py checks that line)."""
    from heliocal.pipeline.vocabulary import AzimuthConvention, FocalSpotDetector

    assert FocalSpotDetector.values() == ("utis", "helios")
    assert AzimuthConvention.values() == ("south", "north-clockwise")
    text = " ".join(CliRunner().invoke(app, ["ingest", "--help"]).stdout.split())
    assert "--focal-spot <utis|helios>" in text
    assert "--azimuth-convention <south|north-clockwise>" in text
