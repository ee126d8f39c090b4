"""Stages: one module per subcommand (ingest, split-knn, fit-coarse, fit-hybrid/aim, sweep,
report, simulate), composing io, models, physics and artifacts. Imported by the CLI only."""
