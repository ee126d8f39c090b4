"""A work directory is untrusted input: hostile work directories and command lines, tried on the
installed heliocal (issue 32).

Each case prepares a work directory (a copy of a small base run on sample_data/juelich/paint:
ingest, split-knn, fit-coarse --preset static-6, fit-hybrid with 20 epochs and one network), or an
input folder, or a command line, runs ``heliocal`` as a user would (a subprocess with a timeout, so
a hang is a result, not a stuck probe), and checks its expectation. It prints one table row per
case: id, the command, the expectation, and ``held`` or ``FAILED`` with what was seen.

Cases ``F*`` are the findings of issue 32 as filed; cases ``E*`` extend the probe (file types,
links, leftovers, manifests, concurrent stages, odd times, targets and options).

Usage::

    .venv/bin/python benchmarks/probe_workdir.py                 # every case
    .venv/bin/python benchmarks/probe_workdir.py F1a E3          # some cases
    .venv/bin/python benchmarks/probe_workdir.py --markdown      # the table as Markdown

The exit code is the number of cases that did not hold (0: all held).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
PAINT = ROOT / "sample_data" / "juelich" / "paint"
HELIOCAL = str(Path(sys.executable).with_name("heliocal"))
RUN_ID = "20250101T000000Z-0123abcd"  # a well-formed run id for hand-made staging folders


@dataclass
class Result:
    code: int | None  # None: killed at the timeout
    out: str
    err: str
    seconds: float

    @property
    def line(self) -> str:
        """The last stderr line (the ``Error: ...`` line), shortened."""
        lines = [x for x in self.err.strip().splitlines() if x.strip()]
        text = lines[-1] if lines else "(no stderr)"
        return text if len(text) <= 150 else text[:147] + "..."

    @property
    def clean(self) -> bool:
        """No traceback and no internal error."""
        return "Traceback" not in self.err and "internal error" not in self.err


@dataclass
class Case:
    id: str
    command: str
    expect: str
    check: Callable[["Probe"], tuple[bool, str]]


CASES: list[Case] = []


def case(id: str, command: str, expect: str):
    def register(func):
        CASES.append(Case(id, command, expect, func))
        return func
    return register


class Probe:
    """The base run and fresh copies of it, and a runner of heliocal with a timeout."""

    def __init__(self, scratch: Path):
        self.scratch = scratch
        self.base = scratch / "base"
        self._n = 0

    def build_base(self) -> None:
        w = ["--workdir", str(self.base), "--quiet"]
        for args in (["ingest", str(PAINT)], ["split-knn"],
                     ["fit-coarse", "--preset", "static-6", "--workers", "1"],
                     ["fit-hybrid", "--max-epochs", "20", "--ensemble", "1", "--workers", "1"]):
            r = self.run(*args, *w, timeout=300)
            if r.code != 0:
                sys.exit(f"base run failed: heliocal {' '.join(args)}: {r.err[-2000:]}")

    def fresh(self, name: str = "case") -> Path:
        """A new empty folder in the scratch space."""
        self._n += 1
        path = self.scratch / f"{self._n:03d}-{name}"
        path.mkdir()
        return path

    def workdir(self) -> Path:
        """A copy of the base work directory (links copied as links)."""
        wd = self.fresh("wd") / "wd"
        shutil.copytree(self.base, wd, symlinks=True)
        return wd

    def run(self, *args, timeout: float = 120, env: dict | None = None,
            cwd: Path | None = None) -> Result:
        t0 = time.perf_counter()
        try:
            p = subprocess.run([HELIOCAL, *map(str, args)], capture_output=True, text=True,
                               timeout=timeout, env={**os.environ, **(env or {})}, cwd=cwd)
            return Result(p.returncode, p.stdout, p.stderr, time.perf_counter() - t0)
        except subprocess.TimeoutExpired as exc:
            out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
            err = exc.stderr.decode() if isinstance(exc.stderr, bytes) else (exc.stderr or "")
            return Result(None, out, err + f"\n(killed after {timeout:g} s: it hangs)",
                          time.perf_counter() - t0)


# ------------------------------------------------------------------------------------------------
# helpers of the cases
# ------------------------------------------------------------------------------------------------
def manifest(wd: Path, stage: str) -> dict:
    return json.loads((wd / f"{stage}.manifest.json").read_text())


def write_manifest(wd: Path, stage: str, data: dict) -> None:
    (wd / f"{stage}.manifest.json").write_text(json.dumps(data, indent=1))


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def victim(p: Probe, text: str = "precious\n") -> Path:
    """A file outside every work directory that no heliocal command may touch."""
    path = p.fresh("outside") / "victim.txt"
    path.write_text(text)
    return path


def intact(path: Path, text: str = "precious\n") -> bool:
    return path.is_file() and not path.is_symlink() and path.read_text() == text


def one_line_error(r: Result) -> bool:
    """Exit 1 (or 2 for usage), one ``Error:`` line, no traceback or internal error."""
    errors = [x for x in r.err.splitlines() if x.startswith("Error:")]
    return r.code in (1, 2) and r.clean and len(errors) == 1


def usage_or_error(r: Result) -> bool:
    """A clear refusal: exit 2 with click's usage message, or one ``Error:`` line."""
    if r.code == 2 and r.clean and "Invalid value" in r.err:
        return True
    return one_line_error(r)


def aim_args(wd: Path, *extra, time_utc: str = "2023-06-21T12:00:00Z",
             target: str = "solar_tower_juelich_lower", heliostat: str = "BE36") -> list:
    args = ["aim", "--workdir", wd, "--heliostat", heliostat, "--target", target]
    if time_utc is not None:
        args += ["--time", time_utc]
    return args + list(extra)


def add_manifest_file(wd: Path, stage: str, rel: str, key: str = "files") -> None:
    data = manifest(wd, stage)
    entry = {"sha256": "0" * 64, "size": 1, "fingerprint": "0" * 64, "artifact": None,
             "run_id": data["run_id"]}
    if key == "files":
        data["files"][rel] = entry
    else:
        data.setdefault(key, []).append(rel)
    write_manifest(wd, stage, data)


def info_json(p: Probe, wd: Path) -> tuple[Result, dict | None]:
    r = p.run("info", wd, "--json", timeout=60)
    try:
        return r, json.loads(r.out)
    except ValueError:
        return r, None


def flagged(doc: dict | None, needle: str) -> bool:
    """Whether ``info --json`` lists ``needle`` among its hostile paths."""
    if doc is None:
        return False
    return any(needle in json.dumps(h) for h in doc.get("hostile", []))


def paint_copy(p: Probe) -> Path:
    """A writable copy of the sample's PAINT folder (with its tower file beside it)."""
    folder = p.fresh("paint")
    shutil.copytree(PAINT, folder / "paint")
    shutil.copy(PAINT.parent / "tower-measurements.json", folder / "tower-measurements.json")
    return folder / "paint"


def calibration_dir(paint: Path, hid: str = "BE36") -> Path:
    return paint / hid / "calibration"


# the cases live in probe_cases.py (findings of issue 32) and probe_cases_more.py (the extension)
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.modules.setdefault("probe_workdir", sys.modules[__name__])  # the case modules import this one
import probe_cases  # noqa: E402,F401  (registers the F cases)
import probe_cases_more  # noqa: E402,F401  (registers the E cases)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ids", nargs="*", help="run only these cases (default: all)")
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    args = parser.parse_args()
    chosen = [c for c in CASES if not args.ids or c.id in args.ids]
    failed = 0
    with tempfile.TemporaryDirectory(prefix="heliocal-probe-") as tmp:
        probe = Probe(Path(tmp))
        t0 = time.perf_counter()
        probe.build_base()
        print(f"base run: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        if args.markdown:
            print("| case | command | expectation | result |\n|---|---|---|---|")
        for c in chosen:
            try:
                held, seen = c.check(probe)
            except Exception as exc:  # noqa: BLE001 - a probe error is a failed case
                held, seen = False, f"probe error {type(exc).__name__}: {exc}"
            failed += not held
            status = "held" if held else "FAILED"
            seen = " ".join(seen.split())
            if args.markdown:
                cell = lambda s: s.replace("|", "\\|")  # noqa: E731
                print(f"| {c.id} | `{cell(c.command)}` | {cell(c.expect)} | {status}: "
                      f"{cell(seen)} |", flush=True)
            else:
                print(f"{c.id:5s} {status:6s} {c.command}\n      expect: {c.expect}\n      "
                      f"seen:   {seen}", flush=True)
    print(f"{len(chosen) - failed} of {len(chosen)} cases held", file=sys.stderr)
    return failed


if __name__ == "__main__":
    sys.exit(main())
