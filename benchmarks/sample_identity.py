"""Run the sample pipeline into a work directory, timing each stage, or compare two such runs.

Used to show that a change of the readers and writers (issue 32's confinement, no-follow writes,
one reader per work directory) changes no artifact and does not slow the stages: run it once on
the code before the change and once after, then compare the two work directories.

``run DIR`` runs, each as its own ``heliocal`` process (so imports count as a user sees them):
``ingest sample_data/juelich/paint``, ``split-knn``, ``fit-coarse``, ``fit-hybrid --mode hybrid
--max-epochs 200``, ``sweep --study 2``, ``report``, ``info DIR`` and ``aim --heliostat BE36``,
and writes the wall time of each to ``DIR/../<name of DIR>.times.json``.

``compare A B`` reads every Parquet artifact of both work directories with pandas and compares
the frames with ``DataFrame.equals`` (exact: same values, dtypes and order), except the columns
the schema declares volatile (wall-clock times); it also compares the ``metrics.json`` of the two
reports without ``git_revision`` and ``inputs`` (the SHA-256 of the input files' bytes, whose
Parquet footers record the revision), and aim's answers (keys that B adds are listed, not counted as
differences), and prints both runs' stage times side by side.

Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/sample_identity.py run /tmp/before
    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/sample_identity.py run /tmp/after
    .venv/bin/python benchmarks/sample_identity.py compare /tmp/before /tmp/after
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAINT = ROOT / "sample_data" / "juelich" / "paint"
HELIOCAL = Path(sys.executable).with_name("heliocal")


def _stages(workdir: Path) -> list[tuple[str, list[str]]]:
    w = ["--workdir", str(workdir)]
    return [
        ("ingest", ["ingest", str(PAINT), *w, "--quiet"]),
        ("split-knn", ["split-knn", *w, "--quiet"]),
        ("fit-coarse", ["fit-coarse", *w, "--quiet", "--workers", "1"]),
        ("fit-hybrid", ["fit-hybrid", *w, "--quiet", "--max-epochs", "200", "--workers", "1"]),
        ("sweep", ["sweep", *w, "--quiet", "--study", "2", "--workers", "1"]),
        ("report", ["report", *w, "--quiet", "--workers", "1"]),
        ("info", ["info", str(workdir), "--json"]),
        ("aim", ["aim", *w, "--heliostat", "BE36", "--time", "2023-06-21T12:00:00Z",
                 "--target", "solar_tower_juelich_lower"]),
    ]


def run(workdir: Path) -> None:
    if workdir.exists():
        shutil.rmtree(workdir)
    times = {}
    for name, args in _stages(workdir):
        t0 = time.perf_counter()
        proc = subprocess.run([str(HELIOCAL), *args], capture_output=True, text=True)
        times[name] = round(time.perf_counter() - t0, 3)
        if proc.returncode != 0:
            sys.exit(f"{name} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
        if name == "aim":
            (workdir.parent / f"{workdir.name}.aim.json").write_text(proc.stdout)
        print(f"{name:12s} {times[name]:8.2f} s", flush=True)
    (workdir.parent / f"{workdir.name}.times.json").write_text(json.dumps(times, indent=1))


def _frames(workdir: Path) -> dict:
    import pandas as pd
    import pyarrow.parquet as pq

    from heliocal.pipeline.artifacts.schemas import all_schemas

    volatile = {s.filename: set(s.volatile) for s in all_schemas()}
    out = {}
    for path in sorted(workdir.glob("*.parquet")):
        df = pq.read_table(path).to_pandas()
        out[path.name] = df.drop(columns=[c for c in df.columns
                                          if c in volatile.get(path.name, set())])
    assert all(isinstance(v, pd.DataFrame) for v in out.values())
    return out


def _common(before, after, path="", new=None):
    """``after`` without the keys ``before`` lacks (recursively), and the dotted names of those
    keys in ``new``: a key the change adds is listed, not counted as a difference."""
    if isinstance(before, dict) and isinstance(after, dict):
        out = {}
        for k, v in after.items():
            if k in before:
                out[k] = _common(before[k], v, f"{path}{k}.", new)
            elif new is not None:
                new.append(f"{path}{k} = {json.dumps(v)[:60]}")
        return out
    return after


def compare(a: Path, b: Path) -> int:
    fa, fb = _frames(a), _frames(b)
    bad = 0
    for name in sorted(set(fa) | set(fb)):
        same = name in fa and name in fb and fa[name].equals(fb[name])
        rows = len(fa[name]) if name in fa else "-"
        print(f"{name:34s} rows {rows!s:>6}  {'equal' if same else 'DIFFERENT'}")
        bad += not same
    ma, mb = (json.loads((d / "report" / "metrics.json").read_text()) for d in (a, b))
    for m in (ma, mb):  # the code's revision, and the SHA-256 of the input files' bytes, whose
        m.pop("git_revision", None)  # Parquet footers hold the revision in their provenance
        m.pop("inputs", None)
    added: list[str] = []
    same = ma == _common(ma, mb, new=added)
    print(f"{'report/metrics.json':34s} {'':11s} {'equal' if same else 'DIFFERENT'}"
          + (f" (keys added: {'; '.join(added)})" if added else ""))
    bad += not same
    aims = [json.loads((d.parent / f"{d.name}.aim.json").read_text()) for d in (a, b)]
    added = []
    same = aims[0] == _common(aims[0], aims[1], new=added)
    print(f"{'aim --heliostat BE36 (JSON)':34s} {'':11s} {'equal' if same else 'DIFFERENT'}"
          + (f" (keys added: {'; '.join(added)})" if added else ""))
    bad += not same
    ta, tb = (json.loads((d.parent / f"{d.name}.times.json").read_text()) for d in (a, b))
    print(f"\n{'stage':12s} {a.name:>12s} {b.name:>12s}  ratio")
    for k in ta:
        print(f"{k:12s} {ta[k]:11.2f}s {tb[k]:11.2f}s  {tb[k] / ta[k]:.3f}")
    total_a, total_b = sum(ta.values()), sum(tb.values())
    print(f"{'all':12s} {total_a:11.2f}s {total_b:11.2f}s  {total_b / total_a:.3f}")
    return 1 if bad else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("workdir", type=Path)
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = parser.parse_args()
    if args.cmd == "run":
        run(args.workdir)
        return 0
    return compare(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
