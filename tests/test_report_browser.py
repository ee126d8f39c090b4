"""The report in a real browser: headless Chromium (Debian's ``chromium`` + ``chromium-driver``,
driven by selenium) opens every page kind of a report from ``file://`` and finds no console
error, no broken link and no broken image; a heliostat id with markup runs no script.

Screenshots go to ``$HELIOCAL_SCREENSHOTS`` (default: the test's temporary folder). Skips, saying
why, where no browser is installed (``.ci/run`` installs it; tests/browser_tools.py).
"""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd
import pytest

from browser_tools import check_page, missing_browser, start_browser
from heliocal.pipeline.artifacts.schemas import all_schemas
from heliocal.pipeline.artifacts.store import write_artifact
from heliocal.pipeline.stages.report import run_report
from test_report import make_workdir

WHY = missing_browser()
#: end to end (a report, then a browser): `make test` runs it, `make test-fast` skips it
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(WHY is not None, reason=f"no browser check: {WHY}")]

#: an id that would open an alert dialog (and fail the page load in selenium) if it ran
EVIL = '<script>alert("x")'


@pytest.fixture(scope="module")
def browser():
    driver = start_browser()
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory) -> Path:
    wd = make_workdir(tmp_path_factory.mktemp("browser"), "sweep")
    for schema in all_schemas():
        if (wd / schema.filename).is_file():
            df = pd.read_parquet(wd / schema.filename)
            df["heliostat_id"] = df["heliostat_id"].replace({"AB02": EVIL})
            write_artifact(df, wd, schema, stage=schema.producer, inputs={})
    run_report(wd, workers=1)
    return wd / "report"


@pytest.mark.parametrize("page", ["index.html", "heliostats/AA01.html", f"heliostats/{EVIL}.html",
                                  "heliostats.html", "field.html", "details.html"])
def test_page_opens_cleanly(browser, report_dir, page, tmp_path):
    shots = Path(os.environ.get("HELIOCAL_SCREENSHOTS", tmp_path))
    shot = shots / ("evil.png" if EVIL in page else page.replace("/", "_") + ".png")
    r = check_page(browser, report_dir / page, shot)
    assert r["console"] == [] and r["links"] == [] and r["images"] == [], r
    assert r["n_links"] >= 6  # the navigation at least
    assert shot.stat().st_size > 10_000
    if page == "index.html":
        # the map links both heliostats (the escaped id resolves to its page: no broken link)
        assert r["n_images"] == 1
        assert browser.execute_script(
            "return document.querySelectorAll('svg a').length;") == 2
        # the sort script works: a click on "test [mrad]" orders the rows ascending
        browser.execute_script("document.querySelectorAll('table.sortable th')[2].click();")
        ids = browser.execute_script("return Array.from(document.querySelectorAll("
                                     "'table.sortable tbody tr td:nth-child(2)'))"
                                     ".map(td => td.textContent);")
        assert ids == ["AA01", EVIL]
    if EVIL in page:
        assert browser.title.startswith(EVIL)  # shown as text, never run
