"""Input readers: PAINT folders, flat calibration logs, row validation and the external sort that
spills large inputs to disk. Imports physics, artifacts and errors; imported by stages."""
