"""Reruns on unchanged inputs answered before pandas or torch is imported (issue 36: "rerunning
any stage on unchanged inputs <= 5 % of its first run").

``heliocal split-knn|fit-coarse|report --incremental`` first goes through
:func:`heliocal.cli.rerun.run_if_unchanged`, which keeps the previous run when its inputs, options
and code are unchanged (:mod:`heliocal.pipeline.artifacts.unchanged`) and otherwise leaves the
command to run as usual. The field is the bundled synthetic sample (4 simulated heliostats) without
SP13's last 5 rows, which a test appends as the changed input.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from heliocal.cli.rerun import COMMANDS, UNCHANGED_LINE, parse, run_if_unchanged
from heliocal.pipeline.io.staged import IngestOptions
from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.stages.report import run_report
from heliocal.pipeline.stages.split import run_split

SYNTH = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic"
OPTIONS = IngestOptions(properties=SYNTH / "paint", tower=SYNTH / "tower-measurements.json")
STAGES = ("split-knn", "fit-coarse")
HEAVY = ("pandas", "numpy", "torch", "sklearn", "scipy", "matplotlib", "pyarrow", "typer")


def _manifest(root: Path, stage: str) -> dict:
    return json.loads((root / f"{stage}.manifest.json").read_text())


def _outputs(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` but the manifests and hidden files, by relative path."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and not p.name.endswith(".manifest.json")
            and not any(part.startswith(".") for part in p.relative_to(root).parts)}


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> tuple[Path, Path]:
    """(a work directory after ingest, split-knn and fit-coarse of the field without SP13's last
    5 rows, the log of those 5 rows)."""
    root = tmp_path_factory.mktemp("unchanged")
    log = pd.read_csv(SYNTH / "calibration_log.csv")
    late = log.index[log["heliostat_id"] == "SP13"][-5:]
    log.drop(index=late).to_csv(root / "old.csv", index=False)
    log.loc[late].to_csv(root / "new.csv", index=False)
    wd = root / "wd"
    run_ingest([root / "old.csv"], wd, OPTIONS)
    run_split(wd)
    run_fit_coarse(wd, batch_size=2, workers=1)
    return wd, root / "new.csv"


def _copy(base, tmp_path: Path) -> Path:
    return shutil.copytree(base[0], tmp_path / "wd")


def _argv(stage: str, wd: Path, *extra: str) -> list[str]:
    return [stage, "--workdir", str(wd), "--incremental", "--quiet", *extra]


@pytest.mark.slow
def test_an_unchanged_rerun_keeps_every_file_and_its_manifest_says_so(base, tmp_path, capsys):
    wd = _copy(base, tmp_path)
    run_report(wd, workers=1)
    before = _outputs(wd)
    runs = {s: _manifest(wd, s) for s in STAGES}
    runs["report"] = _manifest(wd / "report", "report")
    for stage in (*STAGES, "report"):
        assert run_if_unchanged(_argv(stage, wd)) == 0, stage
        assert capsys.readouterr().out == UNCHANGED_LINE + "\n"
        root = wd / "report" if stage == "report" else wd
        now = _manifest(root, stage)
        # a new committed run that names the run it kept and lists its files as they were
        assert now["kept_run"] == runs[stage]["run_id"] != now["run_id"], stage
        assert now["previous_run_id"] == runs[stage]["run_id"]
        assert now["files"] == runs[stage]["files"], stage
        assert now["options"] == runs[stage]["options"] and now["inputs"] == runs[stage]["inputs"]
        assert now["command"] == "heliocal " + " ".join(_argv(stage, wd))
    assert _outputs(wd) == before  # every output byte-identical (pages and figures included)
    # the kept report is the one a full report of these inputs writes now
    run_report(wd, workers=1)
    assert _outputs(wd) == before


@pytest.mark.slow
def test_a_changed_input_artifact_makes_each_stage_compute_again(base, tmp_path):
    wd = _copy(base, tmp_path)
    run_report(wd, workers=1)
    runs = {s: _manifest(wd, s)["run_id"] for s in STAGES}
    run_ingest([base[1]], wd, OPTIONS, append=True)  # SP13 gains 5 rows: measurements.parquet
    assert run_if_unchanged(_argv("split-knn", wd)) is None
    assert _manifest(wd, "split-knn")["run_id"] == runs["split-knn"]  # nothing committed
    assert run_split(wd, incremental=True)["incremental"]["computed"] == 1
    assert run_if_unchanged(_argv("fit-coarse", wd)) is None  # split.parquet changed
    assert _manifest(wd, "fit-coarse")["run_id"] == runs["fit-coarse"]
    assert run_if_unchanged(_argv("report", wd)) is None  # every artifact it reads is an input
    # a committed upstream run that changed only an option of its own counts for the report
    run_fit_coarse(wd, incremental=True, batch_size=2, workers=1)
    run_report(wd, workers=1)
    assert run_if_unchanged(_argv("report", wd)) == 0
    # what the report depends on besides the inputs it recorded: a file of an artifact's name
    # that no run committed (a full report refuses it) ...
    (wd / "hybrid_predictions.parquet").write_bytes(b"made by hand")
    assert run_if_unchanged(_argv("report", wd)) is None
    (wd / "hybrid_predictions.parquet").unlink()
    # ... and the noise floor of a simulated field beside the sources, drawn as the floor
    truth = base[1].parent / "ground_truth.json"
    try:
        truth.write_text(json.dumps({"heliostats": {"SP13": {"noise_floor_mrad": 0.2}}}))
        assert run_if_unchanged(_argv("report", wd)) is None
    finally:
        truth.unlink()
    assert run_if_unchanged(_argv("report", wd)) == 0
    run_fit_coarse(wd, incremental=True, batch_size=2, workers=1, rolling_origins=3)
    assert run_if_unchanged(_argv("report", wd)) is None


@pytest.mark.slow
def test_a_changed_option_makes_each_stage_compute_again(base, tmp_path):
    wd = _copy(base, tmp_path)
    run_report(wd, workers=1)
    for argv in (_argv("split-knn", wd, "--k", "2"), _argv("split-knn", wd, "--seed", "1"),
                 _argv("split-knn", wd, "--method", "random"),
                 _argv("fit-coarse", wd, "--rolling-origins", "3"),
                 _argv("fit-coarse", wd, "--preset", "static-20"),
                 _argv("fit-coarse", wd, "--prior", "field"),
                 _argv("report", wd, "--alert-mrad", "5"),
                 _argv("report", wd, "--figures", "attention"),
                 _argv("report", wd, "--figures-for", "SP13"),
                 _argv("report", wd, "--floor-mrad", "0.1"),
                 # the pages show the folder as given: another spelling is another title
                 _argv("report", Path(os.path.relpath(wd)))):
        assert run_if_unchanged(argv) is None, argv
    assert run_if_unchanged(_argv("report", Path(f"{wd}/"))) == 0  # the same path
    split = run_split(wd, k=2, incremental=True)
    assert split["incremental"]["computed"] == 4 and "field-wide" in split["incremental"]["why_all"]


@pytest.mark.slow
def test_a_deleted_output_or_other_code_is_made_again(base, tmp_path, monkeypatch):
    wd = _copy(base, tmp_path)
    run_id = _manifest(wd, "split-knn")["run_id"]
    (wd / "split.parquet").unlink()
    assert run_if_unchanged(_argv("split-knn", wd)) is None
    assert _manifest(wd, "split-knn")["run_id"] == run_id  # left to the command
    import heliocal.pipeline.artifacts.unchanged as unchanged

    monkeypatch.setattr(unchanged, "code_identity", lambda: "0" * 64)
    assert run_if_unchanged(_argv("fit-coarse", wd)) is None


@pytest.mark.slow
def test_the_command_answers_an_unchanged_rerun_without_heavy_libraries(base, tmp_path):
    wd = _copy(base, tmp_path)
    run_split(wd, incremental=True)  # this code's run, to keep
    probe = ("import sys, json\nfrom heliocal.cli.main import main\n"
             f"sys.argv = ['heliocal'] + {_argv('split-knn', wd)!r}\n"
             "try:\n    main()\nexcept SystemExit as exc:\n    code = exc.code\n"
             f"print(json.dumps([code, sorted(m for m in {list(HEAVY)!r} if m in sys.modules)]),"
             " file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=120)
    assert json.loads(out.stderr.strip().splitlines()[-1]) == [0, []], out.stderr
    assert out.stdout == UNCHANGED_LINE + "\n"


def test_the_early_answer_knows_each_commands_options_as_the_command_does():
    """Every option of :data:`COMMANDS` is the command's own: its spellings, default, choices and
    range as typer declares them (a drifted default would keep a run made with other options)."""
    import typer.main

    from heliocal.cli.main import app

    group = typer.main.get_command(app)
    for stage, opts in COMMANDS.items():
        params = {p.name: p for p in group.commands[stage].params}
        for opt in opts:
            p = params[opt.param]
            assert set(opt.names) <= set(p.opts) | set(p.secondary_opts), (stage, opt.param)
            assert p.default == opt.default, (stage, p.name)
            if opt.kind == "flag":
                assert p.is_flag and not p.secondary_opts, (stage, p.name)
            if opt.kind == "choice":
                kind = p.type_descriptor.annotation
                choices = tuple(m.value for m in kind)
                # only the local scheduler is answered early
                assert choices == opt.choices or opt.choices == ("local",), (stage, p.name)
            if opt.kind == "many":
                assert p.multiple
            if opt.param != "workers":  # a kept run starts no worker; 0 is left to the command
                assert (p.min, p.max) == (opt.low, opt.high), (stage, p.name)


def test_only_plain_spellings_are_answered_early(tmp_path):
    wd = str(tmp_path)
    assert parse(["split-knn", "--workdir", wd, "--k=2", "--incremental"])[1]["k"] == 2
    assert parse(["report", "-w", wd, "--figures-for", "A,B", "--figures-for", "C"])[1][
        "figures_for"] == ["A,B", "C"]
    for argv in (["split-knn", "--k", "4"], ["split-knn", "--k", "2", "--k", "3"],
                 ["split-knn", "--help"], ["split-knn", "--k"], ["split-knn", "--n-test", "-1"],
                 ["split-knn", "--k", "2.0"], ["split-knn", "--incremental=1"],
                 ["fit-coarse", "--heliostat", "A"], ["fit-coarse", "--prior-from", wd],
                 ["fit-coarse", "--scheduler", "dask"], ["fit-coarse", "--workers", "0"],
                 ["report", "--compare", wd], ["report", "--alert-mrad", "nan"],
                 ["sweep", "--incremental"], ["--version"], []):
        assert parse(argv) is None, argv
    assert run_if_unchanged(["split-knn", "--workdir", wd]) is None  # not --incremental
    assert run_if_unchanged(["split-knn", "--workdir", wd, "--incremental"]) is None  # no run
    assert list(tmp_path.iterdir()) == []  # and nothing written
