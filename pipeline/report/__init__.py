"""Report checks: the accuracy regression against a baseline metrics.json and the structural
golden-file comparison. Imports nothing heavy; the CLI's ``report --compare`` uses it."""
