"""Runtime: how work is executed (per-heliostat tasks over local processes or Dask) and the guard
that keeps process-wide settings (torch flags, threads, environment) from leaking out of a call."""
