"""Helpers for tests that tamper with a work directory or look at it as the readers do.

Not a test module (no ``test_`` prefix): imported by test_reliability.py and test_transactions.py.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path


def manifest_of(workdir: Path, rel: str) -> Path:
    """The ``<stage>.manifest.json`` of ``workdir`` that lists ``rel``."""
    for path in sorted(Path(workdir).glob("*.manifest.json")):
        if rel in json.loads(path.read_text())["files"]:
            return path
    raise AssertionError(f"no manifest in {workdir} lists {rel}")


def recommit(workdir: Path, rel: str) -> None:
    """Record the current bytes of ``workdir/rel`` in the manifest that lists it, as if its stage
    had written them (e.g. to simulate a file written by another heliocal version). The content
    fingerprint is left as it was."""
    path = manifest_of(workdir, rel)
    data = json.loads(path.read_text())
    raw = (Path(workdir) / rel).read_bytes()
    data["files"][rel].update(sha256=hashlib.sha256(raw).hexdigest(), size=len(raw))
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def fingerprint(path: Path) -> str:
    """Content fingerprint of the table read back from the Parquet file ``path`` (heliocal's
    table_fingerprint of what pyarrow reads: equal to the one recorded at write time, which
    test_transactions.py checks, so a test can compute it from the file alone)."""
    import pyarrow.parquet as pq

    from heliocal.pipeline.artifacts.schemas import all_schemas

    table = pq.read_table(path)
    from heliocal.pipeline.artifacts.provenance import table_fingerprint

    schema = next(s for s in all_schemas() if s.filename == Path(path).name)
    return table_fingerprint(table, schema)
