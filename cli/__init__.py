"""heliocal.cli: the thin typer command line over :mod:`heliocal.pipeline`."""
