"""What the report reads: every artifact of a work directory that exists (optional stages may be
missing), through the manifests, with a note for each one that is stale.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import pandas as pd

from ..artifacts.schemas import MEASUREMENTS, all_schemas
from ..artifacts.store import (artifact_present, committed_fingerprint, read_artifact,
                               recorded_inputs)
from ..errors import SchemaError, StageInputError

__all__ = [
    "ReportInputs",
    "load_inputs",
]


_OPTIONAL = ("split.parquet", "coarse_params.parquet", "coarse_predictions.parquet",
             "regimes.parquet", "rolling_origin.parquet", "hybrid_predictions.parquet",
             "sweep.parquet", "selection.parquet", "selected_predictions.parquet",
             "field_prior.parquet")


#: Stage that writes each optional artifact (used when its schema is not importable yet).
_PRODUCERS = {"split.parquet": "split-knn", "coarse_params.parquet": "fit-coarse",
              "coarse_predictions.parquet": "fit-coarse", "regimes.parquet": "fit-coarse",
              "hybrid_predictions.parquet": "fit-hybrid",
              "sweep.parquet": "sweep", "selection.parquet": "sweep",
              "selected_predictions.parquet": "sweep", "field_prior.parquet": "fit-coarse"}


# ------------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------------
@dataclass
class ReportInputs:
    """The artifacts of one work directory (``None`` where absent)."""

    workdir: Path
    measurements: pd.DataFrame
    heliostats: pd.DataFrame | None = None
    rejected: pd.DataFrame | None = None
    split: pd.DataFrame | None = None
    coarse_params: pd.DataFrame | None = None
    predictions: pd.DataFrame | None = None  # coarse and hybrid predictions, column `source`
    sweep: pd.DataFrame | None = None
    selection: pd.DataFrame | None = None
    regimes: pd.DataFrame | None = None
    rolling: pd.DataFrame | None = None  # rolling_origin.parquet: the next-day errors
    field_prior: pd.DataFrame | None = None  # field_prior.parquet (fit-coarse --prior field)
    paths: dict[str, Path] = field(default_factory=dict)  # filename -> path of every input read
    notes: list[str] = field(default_factory=list)  # staleness and similar warnings
    # heliostat -> its GP correction on a sky grid (the report stage computes it from the model
    # aim uses, models.gp_heliostat.correction_grid; this package reads no model files)
    gp_maps: dict[str, dict] = field(default_factory=dict)

    def producer(self, filename: str) -> str:
        schema = _schema_for(filename)
        return schema.producer if schema is not None else _PRODUCERS.get(filename, "?")

    def run_hint(self, filename: str) -> str:
        return f"`heliocal {self.producer(filename)} --workdir {self.workdir}`"


def _schema_for(filename: str):
    for schema in all_schemas():
        if schema.filename == filename:
            return schema
    return None


def _read(workdir: Path, filename: str) -> pd.DataFrame | None:
    """An artifact through its declared schema (``None`` when its stage has not written it). A file
    that exists but that no complete run of its stage committed is refused, as every reader does."""
    path = workdir / filename
    schema = _schema_for(filename)
    if schema is None:  # pragma: no cover - every artifact the report reads has a schema
        raise SchemaError(f"{path}: no declared schema (this is a bug in heliocal; please report it)")
    if not artifact_present(workdir, schema):
        return None
    return read_artifact(workdir, schema)


def _stale_notes(workdir: Path, filenames: Iterable[str]) -> list[str]:
    """One note per artifact whose recorded input fingerprints differ from the inputs' committed
    ones (nothing is hashed: the manifests hold the fingerprints)."""
    notes = []
    by_name = {s.name: s for s in all_schemas()}
    for name in filenames:
        schema = _schema_for(name)
        if schema is None:
            continue
        for label, fp in sorted(recorded_inputs(workdir, schema).items()):
            up = by_name.get(label)
            if up is None or fp is None:
                continue
            current = committed_fingerprint(workdir, up)
            if current is not None and current != fp:
                notes.append(f"{name} is stale: {up.filename} changed after it was written (rerun "
                             f"`heliocal {_PRODUCERS.get(name, '?')}`).")
    return notes


def load_inputs(workdir: str | Path) -> ReportInputs:
    """Read every artifact the report can use from ``workdir``.

    Raises
    ------
    StageInputError : ``measurements.parquet`` is missing (run ``ingest`` first).
    SchemaError : an artifact that exists cannot be read.
    """
    workdir = Path(workdir)
    if not artifact_present(workdir, MEASUREMENTS):
        raise StageInputError(f"{workdir / MEASUREMENTS.filename} is missing: run `heliocal ingest "
                              f"SOURCE... --workdir {workdir}` first")
    inp = ReportInputs(workdir=workdir, measurements=_read(workdir, MEASUREMENTS.filename))
    inp.paths[MEASUREMENTS.filename] = workdir / MEASUREMENTS.filename
    tables = {}                  # each file read once (the predictions are pooled below)
    for name in ("heliostats.parquet", "rejected.parquet") + _OPTIONAL:
        df = tables[name] = _read(workdir, name)
        if df is None:
            continue
        inp.paths[name] = workdir / name
        if name == "heliostats.parquet":
            inp.heliostats = df
        elif name == "rejected.parquet":
            inp.rejected = df
        elif name == "split.parquet":
            inp.split = df
        elif name == "coarse_params.parquet":
            inp.coarse_params = df
        elif name == "sweep.parquet":
            inp.sweep = df
        elif name == "selection.parquet":
            inp.selection = df
        elif name == "regimes.parquet":
            inp.regimes = df
        elif name == "rolling_origin.parquet":
            inp.rolling = df
        elif name == "field_prior.parquet":
            inp.field_prior = df
    preds = []
    for name in ("coarse_predictions.parquet", "hybrid_predictions.parquet",
                 "selected_predictions.parquet"):
        df = tables[name]
        if df is not None:
            missing = [c for c in ("heliostat_id", "measurement_id", "model", "split", "error_mrad")
                       if c not in df.columns]
            if missing:
                raise SchemaError(f"{workdir / name} lacks columns {missing}: rerun "
                                  f"{inp.run_hint(name)}")
            inp.paths[name] = workdir / name
            preds.append(df.assign(source=name.removesuffix(".parquet")))
    if preds:
        p = pd.concat(preds, ignore_index=True)
        for col in ("heliostat_id", "measurement_id", "model", "split"):
            p[col] = p[col].astype(str)
        if "selected" not in p.columns:
            p["selected"] = False
        p["selected"] = p["selected"].fillna(False).astype(bool)
        inp.predictions = p
    for col in ("heliostat_id", "measurement_id"):
        inp.measurements[col] = inp.measurements[col].astype(str)
    if inp.split is not None:
        for col in ("heliostat_id", "measurement_id", "split"):
            inp.split[col] = inp.split[col].astype(str)
    inp.notes += _stale_notes(workdir, [n for n in inp.paths if n != MEASUREMENTS.filename])
    return inp
