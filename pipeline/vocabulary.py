"""The choices and defaults of heliocal's stages, each named once.

Light on purpose (the standard library only): the CLI builds its options from this module without
loading numpy, pandas or torch, so ``heliocal --help`` and a mistyped option answer at once, and
the library validates its keyword arguments against the same values. Each choice is a ``str``
:class:`enum.Enum` whose values are the spellings used on the command line, in the library's
keyword arguments and in the artifacts (``docs/nomenclature.md``); typer lists them in ``--help``.
"""

from __future__ import annotations

import enum

__all__ = ["Choice", "CoarsePreset", "RobustStart", "SplitMethod", "SplitMetric", "FineMode",
           "PretrainVariant", "NeuralBaseline", "SweepScreen", "AimModel", "CoarseLoss", "CoarseSolver",
           "CoarsePrior", "SimulatedMounting", "ReportFigures",
           "TrainingDtype", "Scheduler", "DisturbanceKind", "SimulatedType", "FocalSpotDetector",
           "AzimuthConvention", "DEFAULT_BATCH_ROWS", "DEFAULT_TIME_MIN",
           "DEFAULT_TIME_MAX_MARGIN_DAYS", "DEFAULT_MAX_SPOT_DISTANCE_M",
           "DEFAULT_SUN_TOLERANCE_DEG", "HYBRID_BATCH_SIZE", "DEFAULT_STUDY", "DEFAULT_ROLLING_ORIGINS",
           "DEFAULT_FOURIER_BANDS", "OCTAVE_BANDS", "DEFAULT_ALERT_MRAD", "MIN_IMPROVEMENT",
           "STD_ERROR_PSEUDO_INVERSE", "PLAN_MIN_ELEVATION_DEG", "PLAN_DEFAULT_DAYS"]


class Choice(str, enum.Enum):
    """A choice of a stage: its value is the spelling everywhere."""

    def __str__(self) -> str:
        return self.value

    @classmethod
    def values(cls) -> tuple[str, ...]:
        """The spellings, in declaration order."""
        return tuple(m.value for m in cls)


class CoarsePreset(Choice):
    """``fit-coarse --preset``: which kinematic parameters a fit frees (``docs/kinematics.md``);
    auto fits several and selects by validation error."""

    auto = "auto"
    static_6 = "static-6"
    static_14 = "static-14"
    static_20 = "static-20"
    static_28 = "static-28"
    stone_8 = "stone-8"


class ReportFigures(Choice):
    """``report --figures``: whose own figures the report draws (``docs/report.md``, "Whose
    figures"): every heliostat's, those that need attention, or auto (every heliostat's up to
    a small field, else those that need attention)."""

    auto = "auto"
    all = "all"
    attention = "attention"


class TrainingDtype(Choice):
    """``fit-hybrid/sweep --training-dtype``: the precision of the fine model's training
    arithmetic; the kept weights and every reported error are float64 either way."""

    float32 = "float32"
    float64 = "float64"


class RobustStart(Choice):
    """``fit-coarse --robust-start``: grid-search the actuator zero points before LM (auto: when
    the nominal geometry's median error is large)."""

    auto = "auto"
    always = "always"
    never = "never"


class SplitMethod(Choice):
    """``split-knn --method``: the paper's kNN split, and others for comparison."""

    knn = "knn"
    random = "random"
    time = "time"
    azimuth = "azimuth"
    solstice = "solstice"
    balanced = "balanced"
    high_variance = "high-variance"


class SplitMetric(Choice):
    """Distance in sun position of the split."""

    euclidean = "euclidean"
    great_circle = "great-circle"


class FineMode(Choice):
    """``fit-hybrid --mode``: the fine model on the coarse one, the network alone, paper 002's
    pre-trained network, the Gaussian-process correction of the coarse model's pointing."""

    hybrid = "hybrid"
    nn_only = "nn-only"
    pretrained_nn = "pretrained-nn"
    gp = "gp"


class PretrainVariant(Choice):
    """Variant of the ``pretrained-nn`` network (docs/hybrid.md, "The pre-trained network").

    ``residual`` (default): the network learns the correction to the coarse model's inverse
    kinematics in motor steps and starts as the coarse model exactly; ``paper``: paper 002's
    network, pre-trained to imitate the coarse model on simulated calibrations, then fine-tuned.
    """

    residual = "residual"
    paper = "paper"


class NeuralBaseline(Choice):
    """``sweep --baselines``: the neural baselines of the training-size study (comma-separated on
    the command line, or ``none``)."""

    nn_only = "nn-only"
    pretrained_nn = "pretrained-nn"


class SweepScreen(Choice):
    """``sweep --screen``: train one ensemble per heliostat first and the full weight-decay path
    only where it gains enough (on), or the full path everywhere (off)."""

    on = "on"
    off = "off"


class AimModel(Choice):
    """``aim --model``: the model that aims (auto: the sweep's selection, else the best fitted)."""

    auto = "auto"
    coarse = "coarse"
    hybrid = "hybrid"
    nn_only = "nn-only"
    pretrained_nn = "pretrained-nn"
    gp = "gp"


class CoarseLoss(Choice):
    """Loss of the coarse fit: least squares (Levenberg-Marquardt) or a robust loss."""

    linear = "linear"
    soft_l1 = "soft_l1"
    huber = "huber"


class CoarseSolver(Choice):
    """Solver of ``fit-coarse``: the batched LM, or scipy per heliostat (the reference)."""

    batched = "batched"
    scipy = "scipy"


class CoarsePrior(Choice):
    """Prior of ``fit-coarse``'s fits: the default weak one around the nominal geometry only,
    the field's empirical-Bayes prior, or that with spatial neighbours for its mean."""

    none = "none"
    field = "field"
    field_spatial = "field+spatial"


class SimulatedMounting(Choice):
    """How ``simulate`` draws the heliostats' deviations from the nominal geometry: each on its
    own, or from the type's distribution with spatially correlated mounting errors."""

    independent = "independent"
    field = "field"


class Scheduler(Choice):
    """Where per-heliostat work runs: processes on this machine or a Dask cluster."""

    local = "local"
    dask = "dask"


class DisturbanceKind(Choice):
    """Time-dependent disturbances of ``simulate``'s dynamic heliostats."""

    seasonal_tilt = "seasonal_tilt"
    actuator_drift = "actuator_drift"
    gear_error = "gear_error"
    temperature_tilt = "temperature_tilt"


class SimulatedType(Choice):
    """Kinematic types ``simulate`` can draw."""

    juelich = "juelich"
    az_el = "az-el"


class FocalSpotDetector(Choice):
    """``ingest --focal-spot``: the PAINT detector whose focal-spot centroid a row takes (a row
    without it falls back to the other; ``focal_spot_source`` records which)."""

    utis = "utis"
    helios = "helios"


class AzimuthConvention(Choice):
    """``ingest --azimuth-convention``: how a log writes the sun azimuth: ``south`` (0 = south,
    positive toward east, heliocal's own) or ``north-clockwise`` (0 = north, positive toward
    east)."""

    south = "south"
    north_clockwise = "north-clockwise"


#: Rows per batch read from a log (``ingest --batch-rows``): peak memory grows with it, not with
#: the log; the artifacts do not depend on it.
DEFAULT_BATCH_ROWS = 25_000
#: Earliest plausible measurement time (``ingest --time-min``): camera-target calibration logs of
#: today's heliostat fields start decades later; a year like 1700 or 1970 is a logger or export
#: fault.
DEFAULT_TIME_MIN = "1990-01-01T00:00:00Z"
#: The latest plausible measurement time is now plus this many days (``ingest --time-max``
#: overrides it): a calibration cannot have been measured in the future; the margin covers clocks
#: and time zones set wrong.
DEFAULT_TIME_MAX_MARGIN_DAYS = 1
#: ``ingest --max-spot-distance``: a focal spot farther than this from its target's centre is
#: rejected [m] (a spot on another target, or a detector fault).
DEFAULT_MAX_SPOT_DISTANCE_M = 25.0
#: ``ingest --sun-tolerance``: a logged sun position farther than this from NREL SPA's is flagged
#: [deg].
DEFAULT_SUN_TOLERANCE_DEG = 0.1
#: Heliostats per batched training program of ``fit-hybrid`` and ``sweep`` (one task for the
#: workers).
HYBRID_BATCH_SIZE = 32
#: Heliostats in the training-size study by default (``sweep --study``): enough for the paper's
#: figures; the production selection covers every heliostat.
DEFAULT_STUDY = 10
#: Origins per heliostat of fit-coarse's rolling-origin evaluation by default
#: (``fit-coarse --rolling-origins``): one warm-started refit each, spread evenly over the
#: heliostat's calibration days with the last kept. On benchmarks/field.py's 2,000 heliostats
#: (2 workers) fit-coarse took 120.9 s without the evaluation, 208.7 s with 6 origins (1.7x)
#: and 344.0 s with 12 (2.8x): 6 keeps it within twice the fit.
DEFAULT_ROLLING_ORIGINS = 6

#: Relative validation improvement a candidate model needs over the one it would replace: a hybrid
#: over the coarse model in ``sweep``, and in ``fit-coarse`` the fit without a heliostat's episodes
#: and the regime-aware candidates over its first fit. The validation rows lie between the training
#: rows in sun position while the kNN test rows lie at the edge; a network that interpolates the
#: coarse fit's residual structure improves validation by up to about 15 % on static heliostats
#: without improving (or while worsening) the test rows, whereas the dynamic disturbances the fine
#: model is for improve it by 25-45 % (docs/hybrid.md, "Selection").
MIN_IMPROVEMENT = 0.20


#: ``report --alert-mrad``: a heliostat whose model (the one ``aim`` uses) has a mean test error
#: above this is on alert [mrad] (a plant's choice; 2 mrad is the CDF's coarsest reference line).
DEFAULT_ALERT_MRAD = 2.0
#: Fourier bands of the fine network's inputs: every integer 1..32 (see ``FineConfig``).
DEFAULT_FOURIER_BANDS = tuple(float(b) for b in range(1, 33))
#: Fourier bands of the ``hybrid-octaves`` candidate: Tancik et al.'s octaves 1, 2, 4, ..., 32.
OCTAVE_BANDS = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0)


#: ``plan``: lowest sun elevation of a planned row and of the year's aims [deg], and the
#: default length of a plan [days].
PLAN_MIN_ELEVATION_DEG = 10.0
PLAN_DEFAULT_DAYS = 7

#: Appended to a coarse fit's ``fit_status`` (coarse_params.parquet) when ``J^T J`` at the solution
#: could not be inverted and its standard errors come from the pseudo-inverse; the report shows it
#: beside the parameters. One spelling, read by models and report.
STD_ERROR_PSEUDO_INVERSE = ("standard errors from a pseudo-inverse of a singular J^T J: not "
                            "trustworthy")
