"""Benchmark: ``heliocal update`` of two code versions on the same finished full run, alternated.

An incremental stage compares the code identity (the SHA-256 of ``pipeline/**/*.py``) recorded
by the full run with its own, so new code updating a full run built by old code computes every
heliostat again: timing an update of new code normally costs a full run built by it (20 minutes
at 2,000 heliostats). For a change that keeps every result (a faster read, a cached page), this
script times both versions on one full run instead: the ``before`` interpreter's heliocal must be
the code that built ``--full``; the ``after`` one runs with its code identity pinned to the
before's, so that it computes the same heliostats (``--identity ID`` pins both arms to the code
identity ID of the code that built ``--full``, so ``before`` may itself be a later version that
keeps its results). That is only valid if the two updates write
the same artifacts, which the script checks after each pair of runs and refuses to report
otherwise: every Parquet table equal (sweep.parquet's ``wall_time_s`` aside), every other file
byte for byte, with the git revision each report prints and metrics.json's input hashes (which
hold sweep.parquet's) set aside. Manifests are not compared (run ids and times).

Each run copies ``--full`` to ``OUT/<arm>/u`` (the same folder name for both arms: the report's
pages name their work directory) and runs ``heliocal update LOG --workdir u --workers W --json``
there; the arms alternate which goes first. Prints each run's wall time and stage seconds, the
medians per arm and the after/before ratio of the medians. Run it under the machine's lock::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/update_ab.py \\
        --full runs/field-bench/full-2000-w2 --log runs/field-bench/field-2000/update-20.csv \\
        --before /path/to/old/checkout/.venv/bin/python --after .venv/bin/python --runs 3
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq

#: Runs heliocal with the code identity given as the first argument (the ``after`` arm).
_PINNED = """
import sys
if __name__ == "__main__":
    from heliocal.pipeline.artifacts import revision
    revision._CODE = sys.argv.pop(1)
    from heliocal.cli.main import main
    sys.argv[0] = "heliocal"
    main()
"""

_IDENTITY = "from heliocal.pipeline.artifacts.revision import code_identity; print(code_identity())"
_REVISION = "from heliocal.pipeline.artifacts.revision import git_revision; print(git_revision())"


def _ask(python: str, code: str, cwd: Path) -> str:
    return subprocess.run([python, "-c", code], cwd=cwd, check=True, capture_output=True,
                          text=True).stdout.strip()


def _update(arm: str, python: str, identity: str | None, args, out: Path) -> tuple[float, dict]:
    """One update on a fresh copy of the full run; (wall seconds, the --json summary)."""
    folder = out / arm
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    shutil.copytree(args.full, folder / "u", symlinks=True)
    head = [python, str(out / "pinned.py"), identity] if identity else [python, "-m",
                                                                         "heliocal.cli.main"]
    cmd = [*head, "update", str(args.log.resolve()), "--workdir", "u", "--workers",
           str(args.workers), "--json"]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=folder, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode:
        raise SystemExit(f"Error: the {arm} update failed: {done.stderr.strip()[-400:]}")
    return wall, json.loads(done.stdout)


def _differences(a: Path, b: Path, revisions: tuple[str, str]) -> list[str]:
    """The files of the two updated work directories that differ (see the module docstring)."""
    differ = []
    files = sorted({p.relative_to(a) for p in a.rglob("*") if p.is_file()}
                   | {p.relative_to(b) for p in b.rglob("*") if p.is_file()})
    for rel in files:
        if rel.name.endswith("manifest.json") or rel.name == ".heliocal.lock":
            continue
        pa_, pb = a / rel, b / rel
        if not (pa_.exists() and pb.exists()):
            differ.append(f"{rel} (only in one)")
        elif rel.suffix == ".parquet":
            ta, tb = (pq.read_table(p) for p in (pa_, pb))
            drop = ["wall_time_s"] if rel.name == "sweep.parquet" else []
            if not ta.drop(drop).equals(tb.drop(drop)):
                differ.append(str(rel))
        elif rel.name == "metrics.json":
            ma, mb = (json.loads(p.read_text()) for p in (pa_, pb))
            for m in (ma, mb):
                m.pop("inputs", None)
                m.pop("git_revision", None)
            if ma != mb:
                differ.append(str(rel))
        else:
            ba, bb = pa_.read_bytes(), pb.read_bytes()
            for rev in (f"{r}{dirty}".encode() for dirty in ("-dirty", "") for r in revisions):
                ba, bb = ba.replace(rev, b"REV"), bb.replace(rev, b"REV")
            if ba != bb:
                differ.append(str(rel))
    return differ


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", type=Path, required=True, help="a full run built by --before's code")
    ap.add_argument("--log", type=Path, required=True, help="the update's new rows")
    ap.add_argument("--before", required=True,
                    help="python of the code that built --full (or, with --identity, of any "
                         "code that keeps its results)")
    ap.add_argument("--after", default=sys.executable, help="python of the new code")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("runs/update-ab"))
    ap.add_argument("--identity", default=None,
                    help="pin both arms to this code identity: that of the code which built "
                         "--full, when --before is a later version of it")
    args = ap.parse_args()
    args.before, args.after = (os.path.abspath(p) for p in (args.before, args.after))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "pinned.py").write_text(_PINNED)
    here = Path.cwd()
    identity = args.identity or _ask(args.before, _IDENTITY, here)
    revisions = tuple(re.sub(r"-dirty$", "", _ask(py, _REVISION, here)) for py in
                      (args.before, args.after))
    arms = {"before": (args.before, args.identity), "after": (args.after, identity)}
    walls: dict[str, list[float]] = {arm: [] for arm in arms}
    for run in range(args.runs):
        order = list(arms) if run % 2 == 0 else list(reversed(arms))
        for arm in order:
            wall, summary = _update(arm, *arms[arm], args, args.out)
            walls[arm].append(wall)
            stages = " ".join(f"{s['stage']} {s['seconds']:.1f}" for s in summary["stages"])
            ingest = (summary.get("ingest") or {}).get("seconds", float("nan"))
            print(f"run {run + 1} {arm:6s} wall {wall:6.1f} s  (ingest {ingest:.1f} {stages})",
                  flush=True)
        differ = _differences(args.out / "before" / "u", args.out / "after" / "u", revisions)
        if differ:
            raise SystemExit(f"Error: the two updates wrote different artifacts ({len(differ)} "
                             f"files, e.g. {differ[:3]}): the pinned timing is not valid")
    med = {arm: statistics.median(w) for arm, w in walls.items()}
    print(f"medians: before {med['before']:.1f} s, after {med['after']:.1f} s; after / before "
          f"{med['after'] / med['before']:.3f} (the artifacts of every pair equal)")


if __name__ == "__main__":
    main()
