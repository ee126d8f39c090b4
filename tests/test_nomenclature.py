"""docs/nomenclature.md is generated from the declared schemas and must stay in sync.

Regenerate with ``.venv/bin/python -m heliocal.pipeline.artifacts.schemas > docs/nomenclature.md``.
"""

from pathlib import Path

from heliocal.pipeline.artifacts.schemas import all_schemas, nomenclature_markdown


def test_nomenclature_file_is_current():
    path = Path(__file__).resolve().parents[1] / "docs" / "nomenclature.md"
    assert path.read_text(encoding="utf-8") == nomenclature_markdown()


def test_every_stage_artifact_is_documented():
    names = {s.filename for s in all_schemas()}
    assert {"measurements.parquet", "heliostats.parquet", "rejected.parquet", "split.parquet",
            "coarse_params.parquet", "coarse_predictions.parquet", "regimes.parquet", "regime_params.parquet",
            "hybrid_predictions.parquet",
            "sweep.parquet", "selection.parquet"} <= names
    for schema in all_schemas():
        for col in schema.columns:
            assert col.description, (schema.filename, col.name)
