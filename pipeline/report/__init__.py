"""Report: what ``heliocal report`` reads (inputs), the accuracy numbers (metrics.json), the
figures and the pages (Markdown, HTML); and the checks on a report's output: the accuracy
regression against a baseline metrics.json and the structural golden-file comparison. Imports
artifacts, physics and errors; imported by stages (the ``report`` stage) and the CLI."""
