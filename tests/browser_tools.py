"""Open report pages in headless Chromium (selenium): console errors, broken links and images,
full-page screenshots.

Used by tests/test_report_browser.py, and as a script for screenshots of any report::

    .venv/bin/python tests/browser_tools.py runs/sample/report /tmp/shots [PAGE ...]

(default pages: index.html and the first heliostat page). Needs Debian's ``chromium`` and
``chromium-driver`` packages (``.ci/run`` installs them) and selenium (the test extra).
"""

from __future__ import annotations

import shutil
import sys
import urllib.parse
from pathlib import Path

CHROMIUM = ("chromium", "chromium-browser", "google-chrome")
DRIVER = ("chromedriver",)


def missing_browser() -> str | None:
    """Why the browser check cannot run here (None when it can)."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install -e '.[test]' or make install)"
    if not any(shutil.which(b) for b in CHROMIUM):
        return ("no Chromium binary on PATH (Debian: apt-get install chromium chromium-driver; "
                ".ci/run installs them)")
    if not any(shutil.which(d) for d in DRIVER):
        return "no chromedriver on PATH (Debian: apt-get install chromium-driver)"
    return None


def start_browser():
    """Headless Chromium with the browser console log captured (no driver download: the
    system's chromedriver)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = next(shutil.which(b) for b in CHROMIUM if shutil.which(b))
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--hide-scrollbars", "--window-size=1280,900", "--allow-file-access-from-files"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    service = Service(executable_path=next(shutil.which(d) for d in DRIVER if shutil.which(d)))
    return webdriver.Chrome(options=opts, service=service)


def _local_target(url: str) -> Path | None:
    parts = urllib.parse.urlsplit(url)
    if parts.scheme != "file":
        return None
    return Path(urllib.parse.unquote(parts.path))


def check_page(driver, page: Path, shot: Path | None = None) -> dict:
    """Open ``page``; return its problems: ``console`` (SEVERE console messages), ``links``
    (``file:`` links whose file is missing; any other scheme counts too: a report links nothing
    outside itself), ``images`` (images that did not load) and ``title``; save a full-page
    screenshot to ``shot``."""
    driver.get(page.resolve().as_uri())
    # load lazily loaded images now, and wait until every image is done
    driver.execute_script("document.querySelectorAll('img').forEach(i => i.loading = 'eager');")
    driver.set_script_timeout(30)
    driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "Promise.all(Array.from(document.images).map(i => i.complete ? null :"
        " new Promise(r => { i.onload = r; i.onerror = r; }))).then(() => done(true));")
    images = driver.execute_script(
        "return Array.from(document.images).filter(i => !(i.complete && i.naturalWidth > 0))"
        ".map(i => i.src);")
    hrefs = driver.execute_script(
        "return Array.from(document.querySelectorAll('a[href]'))"  # SVG links too
        ".map(a => new URL(a.getAttribute('href'), document.baseURI).href);")
    broken = []
    for h in hrefs:
        target = _local_target(h.split("#", 1)[0])
        if target is None or not target.is_file():
            broken.append(h)
    console = [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
    if shot is not None:
        height = driver.execute_script("return document.documentElement.scrollHeight;")
        driver.set_window_size(1280, min(max(int(height), 900), 16000))
        shot.parent.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(shot))
        driver.set_window_size(1280, 900)
    return {"console": console, "links": broken, "images": images, "title": driver.title,
            "n_links": len(hrefs), "n_images": driver.execute_script(
                "return document.images.length;")}


def main(argv: list[str]) -> int:
    report, out = Path(argv[0]), Path(argv[1])
    pages = argv[2:] or ["index.html",
                         "heliostats/" + sorted(p.name for p in (report / "heliostats").glob("*.html"))[0]]
    why = missing_browser()
    if why:
        print(f"cannot check pages: {why}", file=sys.stderr)
        return 1
    driver = start_browser()
    bad = 0
    try:
        for p in pages:
            shot = out / (p.replace("/", "_").removesuffix(".html") + ".png")
            r = check_page(driver, report / p, shot)
            bad += len(r["console"]) + len(r["links"]) + len(r["images"])
            print(f"{p}: {r['n_links']} links, {r['n_images']} images; console errors "
                  f"{r['console']}, broken links {r['links']}, broken images {r['images']}; "
                  f"screenshot {shot}")
    finally:
        driver.quit()
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
