"""Data cannot leave the work directory or inject markup.

* :func:`safe_child` (the one helper every writer uses to put a data value into a path) refuses
  every name that is not one plain file name inside its folder.
* Heliostat ids are validated at ingest (:data:`HELIOSTAT_ID_RE`).
* report.md escapes input strings (checked by rendering it with markdown-it-py, the CommonMark
  parser rich ships with, with raw HTML enabled as a viewer would), index.html escapes them too.
* End to end: a CSV log with hostile ids and a work directory whose name is HTML goes through
  ingest, split-knn, fit-coarse, fit-hybrid and report: the traversal id is rejected with its
  reason, nothing is written outside the work directory, the odd-but-valid id ``__init__`` is a
  file name and renders as text.
"""

from __future__ import annotations

import csv
import html.parser
import io
from pathlib import Path

import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from markdown_it import MarkdownIt

from heliocal.cli.main import app
from heliocal.pipeline.artifacts.paths import MAX_NAME_BYTES, safe_child
from heliocal.pipeline.artifacts.store import write_artifact
from heliocal.pipeline.errors import UnsafePathError
from heliocal.pipeline.report.pages import md_inline, md_text, render_html, render_markdown
from heliocal.pipeline.stages.report import run_report
from heliocal.pipeline.artifacts.schemas import (HELIOSTAT_ID_RE, HELIOSTATS, MEASUREMENTS,
                                                 REJECTED, heliostat_id_problem,
                                                 suggest_heliostat_id)
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.stages.simulate import write_field

HOSTILE_HTML = "<img src=x onerror=alert(1)>"
TRAVERSAL = "../../../tmp/x/pwned"


# ------------------------------------------------------------------------------------------------
# safe_child
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["BE36.pt", "sky_map_AA31.png", "a..b.json", "H" * 64 + ".json",
                                  "x" * MAX_NAME_BYTES, "ä" * (MAX_NAME_BYTES // 2), "-rf.pt",
                                  HOSTILE_HTML + ".png"])
def test_safe_child_accepts_plain_names(tmp_path, name):
    assert safe_child(tmp_path, name) == tmp_path / name
    assert safe_child(tmp_path / "not" / "made", name) == tmp_path / "not" / "made" / name


@pytest.mark.parametrize("name,why", [
    ("", "it is empty"),
    (".", "names the folder itself or its parent"),
    ("..", "names the folder itself or its parent"),
    (".hidden.pt", "starts with '.'"),
    ("../x.pt", "starts with '.'"),
    ("a/../../x.pt", "path separator"),
    ("sub/x.pt", "path separator"),
    ("/etc/passwd", "path separator"),
    ("..\\..\\x.pt", "starts with '.'"),
    ("a\\b.pt", "path separator"),
    ("x\0.pt", "control character"),
    ("x\n.pt", "control character"),
    ("x" * (MAX_NAME_BYTES + 1), f"longer than {MAX_NAME_BYTES} bytes"),
    ("ä" * (MAX_NAME_BYTES // 2 + 1), f"longer than {MAX_NAME_BYTES} bytes"),
    (None, "it is a NoneType"),
    (Path("x.pt"), "it is a PosixPath"),
])
def test_safe_child_refuses(tmp_path, name, why):
    with pytest.raises(UnsafePathError) as err:
        safe_child(tmp_path, name)
    message = str(err.value)
    assert why in message and "\n" not in message
    assert message.startswith(f"{name!r} cannot be used as a file name in {tmp_path}: ")


def test_safe_child_refuses_a_symlink_leading_outside(tmp_path):
    inside, outside = tmp_path / "wd", tmp_path / "elsewhere"
    inside.mkdir()
    outside.mkdir()
    (inside / "BE36.pt").symlink_to(outside / "BE36.pt")
    (inside / "ok.pt").symlink_to(inside / "real.pt")
    with pytest.raises(UnsafePathError, match="resolves outside the folder"):
        safe_child(inside, "BE36.pt")
    assert safe_child(inside, "ok.pt") == inside / "ok.pt"


def test_safe_child_allows_a_symlinked_folder(tmp_path):
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    assert safe_child(tmp_path / "link", "x.pt") == tmp_path / "link" / "x.pt"


@settings(max_examples=300, deadline=None)
@given(name=st.text(max_size=80))
def test_safe_child_never_returns_a_path_outside(tmp_path_factory, name):
    folder = tmp_path_factory.getbasetemp() / "prop"
    try:
        path = safe_child(folder, name)
    except UnsafePathError:
        return
    assert path.resolve().parent == folder.resolve() and path.name == name


# ------------------------------------------------------------------------------------------------
# heliostat ids
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("hid", ["BE36", "AA31", "H_01", "x.y-z", "_x_", "__init__", "7",
                                 "A" * 64, "AB27.v2_-x"])
def test_valid_ids(hid):
    assert heliostat_id_problem(hid) is None


@pytest.mark.parametrize("hid,problem", [
    (TRAVERSAL, "it starts with '.'"),
    (".hidden", "it starts with '.'"),
    ("-rf", "it starts with '-'"),
    ("A" * 65, "it has 65 characters, more than 64"),
    ("AB27/../AA31", "it contains '/'"),
    ("AB 27", "it contains ' '"),
    ("Jülich1", "it contains 'ü'"),
    (HOSTILE_HTML, "it contains ' ', '(', ')', '<', '=' ..."),
    ("", "it contains"),
    (5, "it is a int, not text"),
])
def test_invalid_ids(hid, problem):
    assert heliostat_id_problem(hid).startswith(problem)


@settings(max_examples=500, deadline=None)
@given(hid=st.text(max_size=100))
def test_suggested_id_is_valid_and_a_safe_file_name(tmp_path_factory, hid):
    new = suggest_heliostat_id(hid)
    assert HELIOSTAT_ID_RE.fullmatch(new) and heliostat_id_problem(new) is None
    folder = tmp_path_factory.getbasetemp()
    assert safe_child(folder, f"error_over_time_{new}.png").parent == folder
    if heliostat_id_problem(hid) is None:  # every valid id is a safe file name as it is
        assert safe_child(folder, f"{hid}.json").name == f"{hid}.json"


GOOD = Path(__file__).resolve().parent / "data" / "good"


def test_log_of_only_traversal_ids_is_refused_saying_how_to_rename(runner, tmp_path):
    """The issue's case: every row of a CSV log has the id ../../../tmp/x/pwned (before: 'rows
    read 10, kept 10' and files written outside the workdir by later stages)."""
    text = (GOOD / "juelich_log_small.csv").read_text()
    lines = text.splitlines()
    (tmp_path / "log.csv").write_text("\n".join([lines[0]] + [TRAVERSAL + l[l.index(","):]
                                                             for l in lines[1:]]) + "\n")
    (tmp_path / "tower-measurements.json").write_text((GOOD / "tower-measurements.json").read_text())
    wd = tmp_path / "deep" / "wd"
    result = runner.invoke(app, ["ingest", str(tmp_path / "log.csv"), "--workdir", str(wd)])
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [
        f"Error: no measurement of {tmp_path / 'log.csv'} could be kept (invalid_heliostat_id: 10): "
        f"heliostat id '{TRAVERSAL}' cannot be used as a file name (it starts with '.'); rename it "
        "in the source to 1-64 ASCII letters, digits, '_', '-' or '.', starting with a letter, "
        "digit or '_', e.g. 'tmp_x_pwned'"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.csv", "tower-measurements.json"]


def test_paint_folder_named_like_markup_is_rejected_by_id(tmp_path):
    """A PAINT heliostat folder whose name is not a valid id: its rows are rejected, the
    properties file is still read (the folder is legitimate otherwise)."""
    import shutil

    from heliocal.pipeline.stages.ingest import ingest

    paint = tmp_path / "paint"
    shutil.copytree(GOOD / "paint_small", paint)
    shutil.copyfile(GOOD / "tower-measurements.json", tmp_path / "tower-measurements.json")
    bad = paint / HOSTILE_HTML
    shutil.copytree(paint / "BE36", bad)
    (bad / "BE36-heliostat-properties.json").rename(bad / f"{HOSTILE_HTML}-heliostat-properties.json")
    m, helio, rejected, info = ingest([paint])
    assert sorted(m["heliostat_id"].unique()) == ["BE36"] and list(helio["heliostat_id"]) == ["BE36"]
    assert len(rejected) == 3 and set(rejected["reason"]) == {"invalid_heliostat_id"}
    assert set(rejected["heliostat_id"]) == {HOSTILE_HTML}
    assert info["rows_read"] == 6


def test_enu_log_and_toml_properties_with_a_traversal_id(tmp_path):
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.stages.ingest import ingest

    props = (GOOD / "enu_properties.toml").read_text().replace("[heliostats.H01]",
                                                                '[heliostats."../H01"]')
    (tmp_path / "props.toml").write_text(props)
    log = (GOOD / "enu_log.csv").read_text().replace("\nH01,", "\n../H01,")
    (tmp_path / "log.csv").write_text(log)
    n_h01 = (GOOD / "enu_log.csv").read_text().count("\nH01,")
    m, _, rejected, _ = ingest([tmp_path / "log.csv"], IngestOptions(properties=tmp_path / "props.toml"))
    assert n_h01 > 0 and len(rejected) == n_h01 and set(rejected["reason"]) == {"invalid_heliostat_id"}
    assert "../H01" not in set(m["heliostat_id"])


def test_parquet_log_integer_ids_are_read_as_digits_and_bad_ones_rejected(tmp_path):
    from heliocal.pipeline.stages.ingest import ingest

    log = pd.read_csv(GOOD / "juelich_log_small.csv")
    ints = log.assign(heliostat_id=log["heliostat_id"].map({"AA31": 31, "AB27": 27}))
    ints.to_parquet(tmp_path / "ints.parquet")
    (tmp_path / "tower-measurements.json").write_text((GOOD / "tower-measurements.json").read_text())
    m, _, rejected, _ = ingest([tmp_path / "ints.parquet"])
    assert sorted(m["heliostat_id"].unique()) == ["27", "31"] and rejected.empty
    hostile = log.assign(heliostat_id=[TRAVERSAL] * 5 + ["AB27"] * 5)
    hostile.to_parquet(tmp_path / "hostile.parquet")
    m, _, rejected, _ = ingest([tmp_path / "hostile.parquet"])
    assert list(m["heliostat_id"].unique()) == ["AB27"]
    assert list(rejected["reason"]) == ["invalid_heliostat_id"] * 5


# ------------------------------------------------------------------------------------------------
# Markdown and HTML escaping
# ------------------------------------------------------------------------------------------------
_MD = MarkdownIt("commonmark", {"html": True}).enable(["table", "strikethrough"])


class _Text(html.parser.HTMLParser):
    """The text and the element names of rendered HTML."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.text, self.tags, self.attrs = [], [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self.attrs += [name for name, _ in attrs]
        if tag == "img":  # only the report's own figure links
            assert dict(attrs)["src"].startswith("figures/") and set(dict(attrs)) == {"src", "alt"}

    def handle_data(self, data):
        self.text.append(data)


def _render(markdown: str) -> _Text:
    parser = _Text()
    parser.feed(_MD.render(markdown))
    return parser


TRICKY = [HOSTILE_HTML, "__init__", "*bold* and _it_", "`code`", "[link](http://x)", "a|b|c",
          "# heading", "> quote", "1. item", "- item", "+ item", "=== ", "~~del~~", "&lt;b&gt;",
          "<!-- c -->", "<script>alert(1)</script>", "x\\", "$x$", "joint_1_tilt_n_rad",
          "![i](x.png)", "---", "a  \nb", "12) x"]


@pytest.mark.parametrize("text", TRICKY)
def test_md_text_renders_as_the_same_text(text):
    got = _render(md_text(text))
    assert "".join(got.text).strip() == " ".join(text.split())
    assert got.tags == ["p"], got.tags  # one paragraph, no other element


@settings(max_examples=1000, deadline=None)
@given(text=st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs", "Cc")),
                    max_size=40))
def test_md_text_renders_any_text_as_itself(text):
    got = _render(md_text(text))
    expected = " ".join(text.split())
    assert "".join(got.text).strip() == expected.replace("\0", "\ufffd")
    assert set(got.tags) <= {"p"}


def test_md_inline_keeps_commands_as_code_spans():
    out = md_inline(f"run `heliocal sweep --workdir runs/{HOSTILE_HTML}` first; *not bold*")
    got = _render(out)
    assert got.tags == ["p", "code"]
    assert "".join(got.text).strip() == f"run heliocal sweep --workdir runs/{HOSTILE_HTML} first; *not bold*"


def test_markdown_table_cells_and_headings_are_escaped():
    blocks = [("h1", f"heliocal report: runs/{HOSTILE_HTML}"), ("h3", "__init__: static-6"),
              ("note", f"{HOSTILE_HTML}: omitted"),
              ("table", ["heliostat", "model"], [[HOSTILE_HTML, "a|b"], ["__init__", "-0.5"]])]
    got = _render(render_markdown(blocks))
    assert "img" not in got.tags and "em" not in got.tags
    assert got.tags.count("strong") == 1  # the report's own "**Note:**", not from the data
    text = "".join(got.text)
    assert f"heliocal report: runs/{HOSTILE_HTML}" in text and "__init__: static-6" in text
    assert HOSTILE_HTML in text and "a|b" in text
    page = render_html(blocks)
    assert "<img src=x" not in page and "&lt;img src=x onerror=alert(1)&gt;" in page


# ------------------------------------------------------------------------------------------------
# report of a work directory written by hand (ids that bypassed ingest)
# ------------------------------------------------------------------------------------------------
_DEFAULTS = {"string": "x", "float64": 0.0, "int64": 0, "bool": False,
             "timestamp": pd.Timestamp("2023-01-01", tz="UTC")}


def _hand_made_workdir(wd: Path, ids: list[str]) -> None:
    rows = [{"heliostat_id": h, "measurement_id": str(i), "sun_azimuth_deg": 10.0 * i,
             "sun_elevation_deg": 20.0 + i} for h in ids for i in range(5)]
    for schema, df in ((MEASUREMENTS, pd.DataFrame(rows)),
                       (HELIOSTATS, pd.DataFrame({"heliostat_id": ids, "n_measurements": 5})),
                       (REJECTED, pd.DataFrame({"source_file": ["a.csv"], "source_row": [1]}))):
        for c in schema.columns:
            if c.name not in df.columns:
                df[c.name] = _DEFAULTS[c.dtype]
        write_artifact(df, wd, schema, stage=schema.producer)


def test_report_escapes_ids_that_bypassed_ingest(tmp_path):
    wd = tmp_path / "wd"
    _hand_made_workdir(wd, [HOSTILE_HTML, "__init__"])
    summary = run_report(wd)
    names = sorted(Path(f).name for f in summary["figures"])
    assert names == sorted(["sky_map___init__.png", f"sky_map_{HOSTILE_HTML}.png"])
    md = (wd / "report" / "report.md").read_text()
    got = _render(md)
    assert got.tags.count("img") == 2 and "onerror" not in got.attrs
    assert got.tags.count("strong") == md.count("> **Note:**")
    assert md.count("\\<img src=x onerror=alert(1)\\>") >= 3
    assert "](figures/sky_map_%3Cimg%20src%3Dx%20onerror%3Dalert%281%29%3E.png)" in md
    page = (wd / "report" / "index.html").read_text()
    assert "<img src=x" not in page


def test_report_refuses_a_traversal_id_that_bypassed_ingest(runner, tmp_path):
    wd = tmp_path / "a" / "b" / "wd"
    _hand_made_workdir(wd, ["AA01", "../../../evil"])
    result = runner.invoke(app, ["report", "--workdir", str(wd), "--quiet"])
    assert result.exit_code == 1
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "Error: 'sky_map_../../../evil.png' cannot be used as a file name in "), lines
    assert not list(tmp_path.rglob("*evil*"))


# ------------------------------------------------------------------------------------------------
# end to end: a log with hostile ids through every writing stage
# ------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_hostile_log_end_to_end(runner, tmp_path):
    """The simulated log of 2 heliostats x 60 rows, ids renamed to a traversal and to __init__,
    in a work directory named like an HTML tag, 4 folders deep (so ../../../ stays in tmp_path)."""
    field = tmp_path / "field"
    write_field(simulate_field(2, seed=5, measurements=(60, 60)), field)
    log = field / "calibration_log.csv"
    rows = list(csv.reader(io.StringIO(log.read_text())))
    first = rows[1][0]
    rename = {first: TRAVERSAL}
    rename.update({r[0]: "__init__" for r in rows[1:] if r[0] != first})
    for r in rows[1:]:
        r[0] = rename[r[0]]
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    hostile_log = tmp_path / "hostile_log.csv"
    hostile_log.write_text(out.getvalue())
    (tmp_path / "tower-measurements.json").write_text((field / "tower-measurements.json").read_text())
    wd = tmp_path / "d1" / "d2" / "d3" / HOSTILE_HTML
    before = {p for p in tmp_path.rglob("*")}

    def run(*args):
        result = runner.invoke(app, [*map(str, args), "--workdir", str(wd)])
        assert result.exit_code == 0, (args, result.stderr)
        return result

    result = run("ingest", hostile_log, "--properties", field / "paint")
    assert "rows read 120, kept 60, rejected 60" in result.stdout
    assert ("60 rows rejected as invalid_heliostat_id: heliostat ids must be 1-64 ASCII letters, "
            "digits, '_', '-' or '.', starting with a letter, digit or '_' (they become file "
            "names); rename them in the source") in result.stdout
    rejected = pd.read_parquet(wd / "rejected.parquet")
    assert set(rejected["reason"]) == {"invalid_heliostat_id"} and len(rejected) == 60
    assert rejected["detail"].iloc[0] == (
        f"heliostat id {TRAVERSAL!r} cannot be used as a file name (it starts with '.'); rename it "
        "in the source to 1-64 ASCII letters, digits, '_', '-' or '.', starting with a letter, "
        "digit or '_', e.g. 'tmp_x_pwned'")
    run("split-knn", "--n-test", "15", "--n-val", "10")
    run("fit-coarse", "--preset", "static-6", "--workers", "1")
    run("fit-hybrid", "--max-epochs", "5", "--ensemble", "1", "--workers", "1")
    run("report")
    assert sorted(p.name for p in (wd / "hybrid" / "hybrid").iterdir()) == ["__init__.json",
                                                                            "__init__.pt"]
    assert sorted(p.name for p in (wd / "report" / "figures").iterdir()) == [
        "error_over_time___init__.png", "field_error_cdf.png", "hybrid_vs_coarse.png",
        "regimes___init__.png", "sky_map___init__.png"]
    assert sorted(p.name for p in (wd / "report" / "heliostats").iterdir()) == ["__init__.html"]
    # nothing was created outside the work directory (the traversal id, had it been kept, would
    # have written d1/d2/d3/tmp/x/pwned.pt from hybrid/hybrid/)
    new = {p for p in tmp_path.rglob("*")} - before
    assert {p for p in new if p != wd and wd not in p.parents} == {
        tmp_path / "d1", tmp_path / "d1" / "d2", tmp_path / "d1" / "d2" / "d3"}
    assert not [p for p in new if "pwned" in p.name]
    md = (wd / "report" / "report.md").read_text()
    got = _render(md)
    assert got.tags.count("img") == 4 and "onerror" not in got.attrs  # the 4 figures
    assert got.tags.count("strong") == md.count("> **Note:**")
    text = "".join(got.text)
    assert f"heliocal report: {wd}" in text and "__init__" in text
    page = (wd / "report" / "index.html").read_text()
    assert "<img src=x" not in page and "&lt;img src=x onerror=alert(1)&gt;" in page
    # aim: the fitted hybrid of __init__ aims; a traversal id is refused in one line
    aim = runner.invoke(app, ["aim", "--workdir", str(wd), "--heliostat", "__init__",
                              "--time", "2023-06-21T10:00:00Z", "--target", "tower_target_lower"])
    assert aim.exit_code == 0, aim.stderr
    bad = runner.invoke(app, ["aim", "--workdir", str(wd), "--heliostat", "../../x", "--sun-azimuth",
                              "10", "--sun-elevation", "40", "--target", "tower_target_lower"])
    assert bad.exit_code == 1 and len(bad.stderr.splitlines()) == 1


# ------------------------------------------------------------------------------------------------
# static guard: data reaches paths only through safe_child
# ------------------------------------------------------------------------------------------------
#: Path joins with a formatted name that are not data-derived, with the reason; keyed by the module's
#: path relative to pipeline/ (cli/ modules as "cli/NAME.py").
NOT_DATA = {
    ("io/paint.py", "hdir / f'{hid}-heliostat-properties.json'"):
        "hid is the name of a folder listed from the source, a plain name by construction",
    ("stages/simulate.py", "hdir / f'{hdir.name}-heliostat-properties.json'"):
        "hdir comes from listing the output folder (removing a previous simulation)",
    ("io/spill.py", "Path(self.folder) / f'{self.name}-{len(self.runs):06d}.parquet'"):
        "a fixed prefix and a counter",
    ("artifacts/manifests.py", "Path(root) / f'{stage}{_MANIFEST_SUFFIX}'"):
        "stage is one of heliocal's stage names (ingest ... report), or a name listed from the "
        "folder that matches the stage pattern (lower-case letters, digits, '-')",
    ("artifacts/transaction.py", "dst.parent / f'.{dst.name}.tmp-{run_id}'"):
        "dst is a destination already confined to the work directory; the name adds a fixed "
        "prefix and the run id, which the manifest check matched against RUN_ID_RE",
    ("artifacts/transaction.py", "self.staging / f'.{target.name}.tmp'"):
        "target is a staged output whose relative path manifests.checked_relative_path already checked",
}


def test_every_formatted_path_join_goes_through_safe_child():
    """In pipeline/ and cli/, ``folder / f"...{x}..."`` only appears in the reviewed places
    above; every other formatted file name is built with ``safe_child(folder, f"...")``."""
    import ast

    root = Path(__file__).resolve().parents[1]
    found = set()
    modules = [(f, f.relative_to(root / "pipeline").as_posix())
               for f in sorted((root / "pipeline").rglob("*.py"))]
    modules += [(f, f.relative_to(root).as_posix()) for f in sorted((root / "cli").rglob("*.py"))]
    assert len(modules) > 30, "the guard reads every module of pipeline/ and cli/"
    for f, key in modules:
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div)
                    and isinstance(node.right, ast.JoinedStr)
                    and any(isinstance(v, ast.FormattedValue) for v in node.right.values)):
                found.add((key, ast.unparse(node)))
    assert found == set(NOT_DATA)
