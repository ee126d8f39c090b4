"""Benchmark: what the stage transactions cost (hashing, fingerprints, fsyncs, the commit).

Part 1 runs the sample pipeline (``ingest`` of sample_data/juelich/paint, ``split-knn``,
``fit-coarse --preset static-6``, ``fit-hybrid --heliostat BE36 --max-epochs 200``, ``report``)
in this process ``--repeats`` times and measures, per stage, the wall time of the stage and the
time spent in the transaction's own work: hashing staged files, fingerprinting tables, hashing
what is read, fsyncs, loading manifests and the commit (manifest write, renames, cleanup).
Nested calls are counted once. It prints medians over the repeats and their ratio.

Part 2 measures the throughput of the two hashes at field scale: SHA-256 of the bytes of a
``measurements.parquet`` of ``--field-rows`` rows (the sample's rows repeated with numbered ids
and jittered floats, about the size of a 2,000-heliostat field) and the content fingerprint of
its table, medians of 3.

Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/transaction_cost.py [--repeats 5]
        [--field-rows 600000]
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAINT = ROOT / "sample_data" / "juelich" / "paint"

_depth = 0
_spent = 0.0


def _timed(func):
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        global _depth, _spent
        if _depth:
            return func(*args, **kwargs)
        _depth += 1
        t0 = time.perf_counter()
        try:
            return func(*args, **kwargs)
        finally:
            _spent += time.perf_counter() - t0
            _depth -= 1

    return wrapper


def _instrument() -> None:
    """Wrap the transaction's own work with :func:`_timed`, in every heliocal module that
    imported the name (a ``from .x import f`` binds its own reference)."""
    import heliocal.pipeline.artifacts.manifests as manifests
    import heliocal.pipeline.artifacts.paths as paths
    import heliocal.pipeline.artifacts.provenance as provenance
    import heliocal.pipeline.artifacts.transaction as transaction

    functions = [(paths, "sha256_of_file")]
    functions += [(transaction, n) for n in ("_fsync_file", "_fsync_dir", "recover", "_apply")]
    functions += [(manifests, n) for n in ("_read_and_hash", "load_manifest")]
    modules = [m for name, m in list(sys.modules.items())
               if name.startswith("heliocal.") and m is not None]
    for home, name in functions:
        original = getattr(home, name)
        wrapped = _timed(original)
        for module in modules:
            if getattr(module, name, None) is original:
                setattr(module, name, wrapped)
    for cls, names in ((transaction.StageTransaction, ("commit", "begin", "abort")),
                       (provenance.Fingerprint, ("add", "hexdigest", "__init__"))):
        for name in names:
            setattr(cls, name, _timed(getattr(cls, name)))


def _stages(workdir: Path):
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.models.config import FineConfig
    from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.report import run_report
    from heliocal.pipeline.stages.split import run_split

    return [
        ("ingest", lambda: run_ingest([PAINT], workdir)),
        ("split-knn", lambda: run_split(workdir)),
        ("fit-coarse", lambda: run_fit_coarse(workdir, preset="static-6", workers=1)),
        ("fit-hybrid", lambda: run_fit_hybrid(workdir, heliostats=["BE36"], workers=1,
                                              config=FineConfig(max_epochs=200))),
        ("report", lambda: run_report(workdir)),
    ]


def part1(repeats: int) -> None:
    global _spent
    _instrument()
    times: dict[str, list[tuple[float, float]]] = {}
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            for name, run in _stages(Path(tmp) / "wd"):
                _spent = 0.0
                t0 = time.perf_counter()
                with contextlib.redirect_stdout(sys.stderr):
                    run()
                times.setdefault(name, []).append((time.perf_counter() - t0, _spent))
    print(f"sample pipeline, {repeats} repeats (medians):")
    print(f"{'stage':<11} {'stage [s]':>10} {'transaction [s]':>16} {'share':>7}")
    total_stage = total_txn = 0.0
    for name, rows in times.items():
        stage = statistics.median(r[0] for r in rows)
        txn = statistics.median(r[1] for r in rows)
        total_stage += stage
        total_txn += txn
        print(f"{name:<11} {stage:>10.3f} {txn:>16.4f} {txn / stage:>7.1%}")
    print(f"{'all':<11} {total_stage:>10.3f} {total_txn:>16.4f} {total_txn / total_stage:>7.1%}")


def part2(rows: int) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from heliocal.pipeline.artifacts.provenance import table_fingerprint
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.artifacts.schemas import MEASUREMENTS

    with tempfile.TemporaryDirectory() as tmp:
        run_ingest([PAINT], Path(tmp) / "wd")
        sample = pq.read_table(Path(tmp) / "wd" / "measurements.parquet")
        table = pa.concat_tables([sample] * (rows // sample.num_rows + 1)).slice(0, rows)
        # distinct rows (as a real field's are): ids numbered, floats jittered, so that the file
        # does not compress to nothing
        import numpy as np

        rng = np.random.default_rng(0)
        cols = {}
        for f in table.schema:
            col = table.column(f.name)
            if f.name == "measurement_id":
                col = pa.array([str(i) for i in range(rows)])
            elif pa.types.is_floating(f.type):
                col = pa.array(col.to_numpy(zero_copy_only=False)
                               + rng.normal(0.0, 1e-3, rows), f.type)
            cols[f.name] = col
        table = pa.table(cols, schema=table.schema)
        path = Path(tmp) / "field.parquet"
        pq.write_table(table, path, compression="zstd", row_group_size=32_768)
        data = path.read_bytes()
        sha, fp = [], []
        for _ in range(3):
            t0 = time.perf_counter()
            hashlib.sha256(data).hexdigest()
            sha.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            table_fingerprint(table, MEASUREMENTS)
            fp.append(time.perf_counter() - t0)
    mb = len(data) / 1e6
    print(f"\nfield scale: measurements.parquet of {rows} rows, {mb:.1f} MB on disk, "
          f"{table.nbytes / 1e6:.0f} MB in memory (medians of 3):")
    print(f"  SHA-256 of the file's bytes: {statistics.median(sha):.3f} s "
          f"({mb / statistics.median(sha):.0f} MB/s)")
    print(f"  content fingerprint of the table: {statistics.median(fp):.3f} s "
          f"({table.nbytes / 1e6 / statistics.median(fp):.0f} MB/s of table data)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--field-rows", type=int, default=600_000)
    args = parser.parse_args()
    import logging

    logging.getLogger("heliocal").setLevel(logging.ERROR)
    part1(args.repeats)
    part2(args.field_rows)


if __name__ == "__main__":
    main()
