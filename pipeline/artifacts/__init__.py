"""Artifacts: declared schemas, atomic writes, provenance and freshness, stage transactions and
manifests, model files and the work-directory lock. Imports only errors; imported by io, models,
stages and report."""
