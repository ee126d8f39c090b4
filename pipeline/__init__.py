"""heliocal.pipeline: the calibration library (plain functions over DataFrames and tensors).

One module per stage (``ingest``, ``split``, ``coarse``, ``hybrid``, ``sweep``, ``report``) plus the
physics (``geodesy``, ``sun``, ``actuators``, ``kinematics``, ``metrics``) and the artifact layer
(``artifacts``: declared schemas, atomic writes, provenance). Library code never prints; the CLI in
:mod:`heliocal.cli` turns :class:`heliocal.pipeline.errors.HeliocalError` into one stderr line.

Conventions, used everywhere (see ``docs/nomenclature.md``):

* Local frame: east-north-up (ENU) metres relative to the plant reference point.
* Sun azimuth [deg]: 0 = south, positive toward east (PAINT/ARTIST); elevation [deg] above horizon.
* Sun vector (unit, toward the sun): e = cos(el) sin(az), n = -cos(el) cos(az), u = sin(el).
* Angular errors in milliradians (``*_mrad``).
"""

__version__ = "0.1.0"
