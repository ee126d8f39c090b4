"""Every preset of many heliostats, as ``fit-coarse`` fits them (:func:`fit_presets`), with each
field prior weighed against the heliostat's own noise (:func:`fit_weighed`, :mod:`.prior_noise`)."""

from __future__ import annotations

from typing import Mapping, Sequence

import torch

from ..errors import check_choice
from ..physics.parameters import HeliostatSpec
from .coarse import SOLVERS, CoarseFit, MeasurementBatch, fit_heliostat, fit_heliostats_batched
from .prior_noise import noise_estimate, reweighed

__all__ = ["fit_presets", "fit_weighed"]


def fit_presets(specs: Sequence[HeliostatSpec], nominals: Sequence[torch.Tensor],
                trains: Sequence[MeasurementBatch], presets: Sequence[str], *,
                solver: str = "batched", loss: str = "soft_l1", f_scale_mrad: float = 1.0,
                robust_start: bool | str = "auto",
                priors: Mapping[str, Mapping[str, tuple]] | None = None) -> list[list[CoarseFit]]:
    """Every preset for each heliostat on its training rows, exactly as ``fit-coarse`` fits them.

    This is the one fitting function of ``fit-coarse`` and of the
    training-size study of ``sweep``, so a study point is what ``fit-coarse`` gives with that
    many training rows. Each heliostat (each entry of the lists; the same heliostat may appear
    several times with different training rows) has its own robust start, shared only by its
    presets.

    Parameters
    ----------
    specs, nominals, trains : per heliostat its spec, nominal parameters (28,) and training rows.
        With ``solver="batched"`` all must share one kinematic and actuator type.
    presets : preset names.
    solver : ``batched`` (per preset one :func:`~.coarse.fit_heliostats_batched` program for all) or
        ``scipy`` (one :func:`~.coarse.fit_heliostat` per heliostat and preset).
    loss, f_scale_mrad, robust_start : see :func:`~.coarse.fit_heliostat`.
    priors : heliostat id -> preset -> :func:`~.coarse.fit_heliostat`'s ``prior`` (mean (28,), sigma
        (28,)); a heliostat or preset it does not name gets the default prior. A field prior
        is weighed against the heliostat's own noise (:func:`fit_weighed`).

    Returns
    -------
    Per heliostat, its fits in the order of ``presets``.
    """
    check_choice(solver, "solver", "fit_presets", SOLVERS)
    caches = [{} for _ in specs]
    kwargs = {"loss": loss, "f_scale_mrad": f_scale_mrad, "robust_start": robust_start}
    own = [(priors or {}).get(spec.heliostat_id) or {} for spec in specs]
    per_preset = [fit_weighed(specs, nominals, trains, preset, solver=solver, caches=caches,
                              priors=[mine.get(preset) for mine in own], **kwargs)
                  for preset in presets]
    return [[fits[k] for fits in per_preset] for k in range(len(specs))]


def _solve(specs, nominals, trains, preset: str, solver: str, caches, priors, starts,
           kwargs) -> list[CoarseFit]:
    if solver == "scipy":  # cold: an explicit start would also move the prior's centre
        return [fit_heliostat(s, n, t, preset, start_cache=c, prior=p, **kwargs)
                for s, n, t, c, p in zip(specs, nominals, trains, caches, priors)]
    return fit_heliostats_batched(specs, nominals, trains, preset, start_caches=caches,
                                  priors=priors, starts=starts, **kwargs)


def fit_weighed(specs: Sequence[HeliostatSpec], nominals: Sequence[torch.Tensor],
                trains: Sequence[MeasurementBatch], preset: str, *, solver: str,
                caches: Sequence[dict], priors: Sequence, **kwargs) -> list[CoarseFit]:
    """One preset's fits of the heliostats (``solver``: ``batched`` or ``scipy``; ``caches``
    their robust starts; ``priors`` per heliostat :func:`~.coarse.fit_heliostat`'s ``prior`` or
    None; ``kwargs`` the fit's loss, f_scale_mrad, robust_start), each field prior weighed
    against the heliostat's own noise: a fit whose own noise differs from the field's by more
    than :data:`~.prior_noise.NOISE_REFIT_FACTOR` is solved again under it, warm-started at its
    first solution (:mod:`.prior_noise`). A re-solved fit's ``wall_time_s`` counts both solves.
    Each fit under a field prior records the heliostat's own noise estimate (``own_noise_mrad``,
    from the first solve) and the noise its prior was weighed against in the solve it returns
    (``prior_noise_mrad``: the own estimate where re-solved, the field's elsewhere)."""
    priors = list(priors)
    fits = _solve(specs, nominals, trains, preset, solver, caches, priors, None, kwargs)
    for prior, fit in zip(priors, fits):
        if (estimate := noise_estimate(prior, fit)) is not None:
            fit.prior_noise_mrad, fit.own_noise_mrad = estimate
    again = {k: p for k, (prior, fit) in enumerate(zip(priors, fits))
             if (p := reweighed(prior, fit)) is not None}
    if not again:
        return fits
    idx = sorted(again)
    refits = _solve([specs[k] for k in idx], [nominals[k] for k in idx],
                    [trains[k] for k in idx], preset, solver, [caches[k] for k in idx],
                    [again[k] for k in idx], [fits[k].params for k in idx], kwargs)
    for k, refit in zip(idx, refits):
        refit.wall_time_s += fits[k].wall_time_s
        # the first solve's estimate, which reweighed put on every field entry of the prior
        refit.own_noise_mrad = refit.prior_noise_mrad = fits[k].own_noise_mrad
        fits[k] = refit
    return fits
