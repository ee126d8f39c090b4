"""The coarse refits of ``sweep``'s training-size study, with the field prior ``fit-coarse`` gave
each heliostat (issue 34).

A study point is what ``fit-coarse`` gives with that many training rows. When ``fit-coarse``
fitted under a field prior (``--prior field``, ``field+spatial``, ``--prior-from``), that is a
fit under the heliostat's own prior: the one of its leave-out fold, which never saw its rows
(docs/field_prior.md). The study rebuilds that prior from coarse_params.parquet
(:func:`heliostat_priors`: ``prior_mean``, ``prior_sigma`` and ``prior_field_noise_mrad`` of
each preset's rows) and refits every size under it; such rows keep the preset's name, as
fit-coarse's full-size rows do, and the hybrids and the GP of each size train on that refit of
the selected preset as they train on fit-coarse's fit at the full size. The same presets
fitted without the field prior (the default weak prior around the nominal geometry) are the
model ``<preset>+no-field-prior`` at every size, the full one included (fit-coarse did not fit
it): the two curves show what the prior does with few rows. Without a field prior nothing
changes: the refits are the default prior's, named by the preset, and there is no
``+no-field-prior`` model.

The prior does not depend on the training size: a heliostat's fold's prior was estimated from
the other heliostats' rows, so the same prior is fit-coarse's at any size of this heliostat's
training rows.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..artifacts.schemas import COARSE_PARAMS
from ..artifacts.store import read_artifact
from ..models.coarse import normal_errors_mrad
from ..models.coarse_presets import fit_presets
from ..models.field_prior import default_sigma
from ..models.prior_noise import HeliostatPrior
from ..physics.parameters import PARAMETER_NAMES
from .sweep_inputs import sweep_row

__all__ = ["NO_FIELD_PRIOR", "no_field_prior_name", "prior_rows_of", "heliostat_priors",
           "study_coarse_rows"]

log = logging.getLogger("heliocal.sweep")

#: Suffix of the study's model of a preset fitted without the field prior:
#: ``<preset>+no-field-prior`` (only where fit-coarse fitted the preset under one).
NO_FIELD_PRIOR = "no-field-prior"

_PRIOR_COLUMNS = ["heliostat_id", "preset", "parameter_index", "prior_mean", "prior_sigma",
                  "prior_field_noise_mrad"]


def no_field_prior_name(preset: str) -> str:
    """``<preset>+no-field-prior``: the study's model of ``preset`` fitted without the field
    prior."""
    return f"{preset}+{NO_FIELD_PRIOR}"


def prior_rows_of(workdir: str | Path, ids: Sequence[str]) -> dict[str, pd.DataFrame]:
    """heliostat -> its coarse_params.parquet rows that record a field prior (columns
    ``preset``, ``parameter_index``, ``prior_mean``, ``prior_sigma``,
    ``prior_field_noise_mrad``) of the heliostats ``ids``; empty without a field prior. A
    coarse_params.parquet from before ``prior_field_noise_mrad`` gives none (with a warning:
    the prior cannot be rebuilt faithfully; run fit-coarse again)."""
    if not ids:
        return {}
    df = read_artifact(workdir, COARSE_PARAMS, heliostats=list(ids))
    if "prior_mean" not in df.columns or df["prior_mean"].notna().sum() == 0:
        return {}
    if "prior_field_noise_mrad" not in df.columns:
        log.warning("coarse_params.parquet records field priors but not the field noise they "
                    "were weighed against: the training-size study refits without the field "
                    "prior (run `heliocal fit-coarse` again)")
        return {}
    df = df.loc[df["prior_mean"].notna() & ~df["preset"].astype(str).str.contains("+", regex=False),
                _PRIOR_COLUMNS]
    return {str(h): g.drop(columns="heliostat_id").reset_index(drop=True)
            for h, g in df.groupby("heliostat_id", sort=True)}


def heliostat_priors(rows: pd.DataFrame | None, nominal) -> dict[str, HeliostatPrior]:
    """preset -> the :class:`HeliostatPrior` fit-coarse gave the heliostat (``rows``: its
    :func:`prior_rows_of` rows; ``nominal`` (28,) its nominal parameters).

    coarse_params records the prior on the free parameters; the others are as
    :meth:`~heliocal.pipeline.models.field_prior.PriorEstimate.heliostat_prior` makes every
    parameter without a field prior: mean the nominal value, sigma the default prior's, noise 1
    mrad (a fixed parameter stays at the prior's mean, the nominal value). The entries with a
    ``prior_field_noise_mrad`` are the field's, weighed against that noise; a prior without
    any (the field's noise unknown) is never re-weighed (``field`` None), as fit-coarse's."""
    if rows is None or rows.empty:
        return {}
    nominal = np.asarray(nominal, np.float64)
    out = {}
    for preset, g in rows.groupby("preset", sort=True):
        at = g["parameter_index"].to_numpy(int)
        mean, sigma = nominal.copy(), default_sigma(nominal)
        noise = np.ones(len(PARAMETER_NAMES))
        field = np.zeros(len(PARAMETER_NAMES), bool)
        mean[at], sigma[at] = g["prior_mean"].to_numpy(float), g["prior_sigma"].to_numpy(float)
        field_noise = g["prior_field_noise_mrad"].to_numpy(float)
        field[at] = np.isfinite(field_noise)
        noise[at[field[at]]] = field_noise[field[at]]
        out[str(preset)] = HeliostatPrior(mean, sigma, noise, field if field.any() else None)
    return out


def study_coarse_rows(h, small: Sequence[int], fitted: tuple, masks: dict, dists: dict,
                      base_preset: str, coarse_options: dict,
                      priors: dict[str, HeliostatPrior]) -> tuple[list[dict], dict]:
    """The study's coarse rows of one heliostat ``h`` (a
    :class:`~.sweep_inputs.SweepHeliostat`) and the selected preset's refits per size below the
    full one (``{n: params (28,)}``, the hybrids' bases).

    Every preset of ``fitted`` is fitted as fit-coarse fits it at each size of ``small``, each
    size its own robust start, under ``priors`` (preset -> its :class:`HeliostatPrior`,
    :func:`heliostat_priors`; empty: the default prior); presets fit-coarse did not fit are
    fitted at the full size too (its production rows hold those it did). Each preset with a
    field prior is also fitted without it at each size of ``small`` and at the full size
    (model :func:`no_field_prior_name`). ``masks``, ``dists``: per size the training rows and
    the test rows' mean distance to them."""
    jobs = [(n, fitted, False) for n in small]
    missing = tuple(p for p in fitted if p not in h.coarse)
    if missing:
        jobs.append((h.n_full, missing, False))
    plain = tuple(p for p in fitted if p in priors)
    if plain:
        jobs += [(n, plain, True) for n in [*small, h.n_full]]
    rows: list[dict] = []
    bases: dict = {}
    for (names, without), sizes in _jobs_by_presets(jobs).items():
        for n, fits, wall in _fit_sizes(h, sizes, names, masks,
                                        None if without else {h.hid: priors}, coarse_options):
            for fit in fits:
                with torch.no_grad():
                    err = normal_errors_mrad(fit.params, h.spec, h.data).numpy()
                model = no_field_prior_name(fit.preset) if without else fit.preset
                rows.append(sweep_row(h.hid, model, n, float("nan"), 0, err, h.labels, masks[n],
                                      dists[n], fit.preset, wall))
                if not without and fit.preset == base_preset and n < h.n_full:
                    bases[n] = fit.params
    return rows, bases


def _jobs_by_presets(jobs) -> dict[tuple, list[int]]:
    """(presets, without the field prior) -> the training sizes fitted so, in job order."""
    grouped: dict[tuple, list[int]] = {}
    for n, names, without in jobs:
        grouped.setdefault((names, without), []).append(n)
    return grouped


def _fit_sizes(h, sizes: Sequence[int], names: tuple, masks: dict, priors, coarse_options):
    """``(n, fits, wall_time_s per fit)`` of heliostat ``h`` at each size of ``sizes``: one
    :func:`fit_presets` call holding every size as its own entry (each its robust start and its
    solve, as fit-coarse's heliostats of a chunk), so the batched solver runs one program per
    preset instead of one per size."""
    t0 = time.perf_counter()
    fits = fit_presets([h.spec] * len(sizes), [h.nominal] * len(sizes),
                       [h.data.subset(masks[n]) for n in sizes], names, priors=priors,
                       **coarse_options)
    wall = (time.perf_counter() - t0) / (len(names) * len(sizes))
    return [(n, f, wall) for n, f in zip(sizes, fits)]
