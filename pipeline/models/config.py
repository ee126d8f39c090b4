"""Settings of the fine model and its training (:class:`FineConfig`), of the training along the
weight-decay path (:class:`PathConfig`) and of the sweep's screen (:class:`ScreenConfig`): plain
frozen dataclasses, light to import (the CLI reads their defaults for ``--help`` without loading
torch).
"""

from __future__ import annotations
import dataclasses
from dataclasses import dataclass
from typing import Mapping
from ..errors import ParameterError, check_float, check_int
from ..vocabulary import DEFAULT_FOURIER_BANDS, TrainingDtype

__all__ = [
    "PathConfig",
    "ScreenConfig",
    "FineConfig",
    "TRAINING_DTYPES",
    "ensemble_seeds",
]

_FUNC = "fit_hybrid"

#: Precisions of the fine model's training arithmetic (``FineConfig.training_dtype``).
TRAINING_DTYPES = TrainingDtype.values()


def ensemble_seeds(seed: int, ensemble: int) -> list[int]:
    """Seeds of the ``ensemble`` networks of the model with seed ``seed``:
    ``seed * ensemble + k`` for k = 0 .. ensemble - 1 (one network: the seed itself; different
    seeds never share a network)."""
    return [int(seed) * int(ensemble) + k for k in range(int(ensemble))]


@dataclass(frozen=True)
class FineConfig:
    """Settings of the fine network and its training (``__init__`` only stores them).

    Attributes
    ----------
    depth : hidden layers (paper 000: 14).
    width : neurons per hidden layer (paper 000: 2).
    fourier_bands : frequencies ``b`` of the Fourier features of the normalised steps [1/range].
    env : names of ``env_*`` columns (without the prefix) used as extra inputs.
    learning_rate : Adam step size.
    max_epochs : epoch budget (full batch: one step per epoch).
    patience : epochs without a validation improvement before a member stops.
    output_scale_factor : multiplies :data:`OUTPUT_SCALE` (1 for ``hybrid``).
    fourier_decay : the Fourier feature of band ``b`` has amplitude ``b ** -fourier_decay``
        (0: all 1, Tancik et al.; > 0: a smoothness prior, see :class:`FeatureEncoder`).
    ensemble : networks per model; the model's deviation is their mean (see
        :func:`ensemble_seeds`). Averaging removes most of the dependence on the initial
        weights, which for a 14 x 2 network is large (docs/hybrid.md, "Ensembles").
    training_dtype : ``"float32"`` or ``"float64"``: the precision of the training's arithmetic
        (network and kinematics); the kept weights, every prediction and every reported error
        are float64. float32 trains about 1.7x faster and selects as well (docs/hybrid.md,
        "Training precision"); float64 for exact comparisons of trainings.

    The default bands are every integer 1..32: a complete Fourier series of the normalised
    steps, so a disturbance with any period of at least ``max_steps / 32`` steps (a gear or
    worm period, say) is a linear function of the inputs. Octave bands (1, 2, 4, ..., 32) can
    only express periods near ``max_steps / 2**k`` (docs/hybrid.md, "Why SS48 missed").
    """

    depth: int = 14
    width: int = 2
    fourier_bands: tuple[float, ...] = DEFAULT_FOURIER_BANDS
    env: tuple[str, ...] = ()
    learning_rate: float = 3e-3
    max_epochs: int = 800
    patience: int = 200
    output_scale_factor: float = 1.0
    fourier_decay: float = 0.0
    ensemble: int = 4
    training_dtype: str = "float32"

    def validated(self) -> "FineConfig":
        check_int(self.depth, "depth", _FUNC, 0)
        check_int(self.width, "width", _FUNC, 1)
        check_float(self.learning_rate, "learning_rate", _FUNC, 0.0, None, low_inclusive=False)
        check_int(self.max_epochs, "max_epochs", _FUNC, 0)
        check_int(self.patience, "patience", _FUNC, 1)
        check_float(self.output_scale_factor, "output_scale_factor", _FUNC, 0.0, None,
                    low_inclusive=False)
        for b in self.fourier_bands:
            check_float(b, "fourier_bands", _FUNC, 0.0, None, low_inclusive=False)
        check_float(self.fourier_decay, "fourier_decay", _FUNC, 0.0, None)
        check_int(self.ensemble, "ensemble", _FUNC, 1)
        if self.training_dtype not in TRAINING_DTYPES:
            raise ParameterError(f"The 'training_dtype' parameter of {_FUNC} must be one of "
                                 f"{', '.join(TRAINING_DTYPES)}. Got {self.training_dtype!r} "
                                 "instead.")
        return self

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["fourier_bands"] = list(self.fourier_bands)
        d["env"] = list(self.env)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "FineConfig":
        d = dict(d)
        d["fourier_bands"] = tuple(float(b) for b in d.get("fourier_bands", ()))
        d["env"] = tuple(d.get("env", ()))
        return cls(**d)


@dataclass(frozen=True)
class PathConfig:
    """How the hybrid's networks are trained along the weight-decay path (strong to weak).

    Attributes
    ----------
    warm_start : continuation (default): the first weight decay trains from the seeded initial
        weights, every later one from the previous weight decay's best-validation weights (its
        Adam moments are not kept); each trains for at most ``stage_epochs`` epochs and stops
        after ``stage_patience`` epochs without a validation improvement. ``False``: every
        weight decay trains from the seeded initial weights with :class:`FineConfig`'s budget
        (``max_epochs``, ``patience``), independently of the others.
    stage_epochs, stage_patience : the budget of each weight decay with ``warm_start``.

    Why these defaults: docs/hybrid.md ("Training the path"): on 46 simulated heliostats and
    the Jülich sample the continuation selects as well as independent trainings (within their
    seed-to-seed spread) for about a third of the compute.
    """

    warm_start: bool = True
    stage_epochs: int = 200
    stage_patience: int = 50

    def validated(self) -> "PathConfig":
        check_int(self.stage_epochs, "stage_epochs", "sweep", 0)
        check_int(self.stage_patience, "stage_patience", "sweep", 1)
        return self

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class ScreenConfig:
    """The sweep's screen: how far a heliostat's weight-decay path is trained before the sweep
    asks whether the rest is worth it (:mod:`heliocal.pipeline.stages.sweep_screen`,
    docs/hybrid.md "The screen").

    Attributes
    ----------
    enabled : ``False`` trains every heliostat's full path (``sweep --screen off``).
    stages : the screen is the first band set's path up to its ``stages``-th weight decay (3: 1,
        0.1 and 0.01 on the default grid); where it passes, the path goes on from there and the
        other band sets are trained, so the screen costs a passing heliostat nothing.
    share : the screen's margin is ``share`` x the rule's network margin
        (``SelectionRule.min_improvement``): the rest of the path may gain more than its start,
        so the screen asks for part of the margin only. A rule whose network margin is not
        positive cannot be screened for (every heliostat trains its path).
    stage_gain : where the screen passes, each band set trains its first ``stages`` weight
        decays and goes on, one weight decay at a time, while the last one raised the band
        set's best relative gain over the coarse model (on the weighted validation rows) by at
        least this much; ``0`` trains every band set's whole path. Why 0.01:
        docs/experiments/sweep-screen.md, "Where the path stops gaining".
    """

    enabled: bool = True
    stages: int = 3
    share: float = 0.5
    stage_gain: float = 0.01

    def validated(self) -> "ScreenConfig":
        check_int(self.stages, "stages", "sweep_screen", 1)
        check_float(self.share, "share", "sweep_screen", 0.0, 1.0)
        check_float(self.stage_gain, "stage_gain", "sweep_screen", 0.0, 1.0)
        return self

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
