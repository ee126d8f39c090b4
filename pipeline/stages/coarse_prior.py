"""``fit-coarse``'s field prior (issue 34): the empirical-Bayes prior every heliostat's fit gets
from the other heliostats of its group (:mod:`heliocal.pipeline.models.field_prior`), the
field-prior geometry (a candidate of every heliostat's selection, and the model of a heliostat
without training rows), and ``field_prior.parquet``. :mod:`.fit_coarse` runs the stage.

How (``--prior field``; ``none``, the default, fits without it; ``field+spatial`` adds the
neighbours' mean where it helps):

1. The *sample* of each group (kinematic type, actuator type, geometry source): its heliostats
   with the most rows, at most :data:`SAMPLE_SIZE` (all of them in most fields), are fitted
   with every preset of the run under the default weak prior, each on all its rows that are not
   test rows (the stage passes them: a plant's history, heliostats the split skipped included).
2. Per preset the prior is estimated from those fits (per fold: leave-out,
   :class:`~heliocal.pipeline.models.field_prior.GroupPrior`).
3. Fit -> prior -> refit, :data:`PRIOR_ROUNDS` = 1 time: every heliostat is fitted by the stage
   under that prior (MAP: the prior's rows in the batched LM). More rounds (refitting the
   sample under its priors and estimating again, the EM step) would let a heliostat's own fit
   reach its own prior through the other heliostats' refits, which the leave-out forbids.

A parameter gets the field's prior only where :data:`~heliocal.pipeline.models.field_prior.MIN_HELIOSTATS`
well-determined heliostats (outside the heliostat's own fold) estimate it; elsewhere, and in a
group without them, the fit keeps the default prior, so such a field is fitted exactly as with
``--prior none``. With ``--prior-from OTHER`` the prior of OTHER's field_prior.parquet is used
(no estimation here; the run's provenance records ``prior_from`` among its options).
"""

from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pandas as pd
import torch

from ..artifacts.schemas import FIELD_PRIOR
from ..artifacts.manifests import ACTIVE_TRANSACTION
from ..artifacts.paths import artifact_path
from ..artifacts.store import read_artifact
from ..errors import ParameterError, StageInputError
from ..models.coarse import CoarseFit, MeasurementBatch, predict
from ..models.coarse_presets import fit_presets
from ..models.prior_noise import HeliostatPrior
from ..models.field_prior import (MIN_HELIOSTATS, FitSample, GroupPrior, PriorEstimate,
                                  deviation, group_key)
from ..physics.metrics import mean_or_nan as _mean
from ..physics.parameters import PARAMETER_NAMES, HeliostatSpec, nominal_parameters, preset_mask
from ..runtime.parallel import map_tasks
from ..vocabulary import CoarsePrior

__all__ = ["PRIOR_MODES", "PRIOR_ROUNDS", "SAMPLE_SIZE", "FIELD_PRIOR_MODEL", "PriorPlan",
           "plan_field_prior", "field_prior_name", "is_field_prior", "field_prior_fit",
           "with_field_prior", "field_prior_note", "zero_row_outputs", "finish_table", "attach_prior_columns",
           "prior_frame", "summary_of", "with_deviations", "heliostat_groups"]

log = logging.getLogger("heliocal.coarse")

#: Choices of ``fit-coarse --prior``.
PRIOR_MODES = CoarsePrior.values()

#: Fits of the sample before the final fit: 1 = fit -> prior -> final fit (module docstring: a
#: second round, the EM step, would break the leave-out).
PRIOR_ROUNDS = 1

#: Heliostats per group whose fits estimate the prior (those with the most training rows).
SAMPLE_SIZE = 256

#: Suffix of the field-prior geometry's model name: ``<preset>+field-prior`` is the group's
#: field-prior geometry, the nominal geometry moved by the prior mean of ``<preset>`` (the
#: run's first preset, the one the field determines best).
FIELD_PRIOR_MODEL = "field-prior"


def field_prior_name(preset: str) -> str:
    """``<preset>+field-prior``: the model name of the field-prior geometry of ``preset``."""
    return f"{preset}+{FIELD_PRIOR_MODEL}"


def is_field_prior(model: str) -> bool:
    """Whether a coarse model name is a field-prior geometry."""
    return str(model).split("+")[1:2] == [FIELD_PRIOR_MODEL]


@dataclass
class PriorPlan:
    """What the stage gives its fits: per heliostat and preset the prior, per heliostat the
    field-prior geometry, and field_prior.parquet's rows (without the expected errors, which
    :func:`finish_table` adds once the fits are evaluated)."""

    mode: str
    prior_from: str | None
    priors: dict[str, dict[str, tuple]] = field(default_factory=dict)
    geometry: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)
    table: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(
        columns=FIELD_PRIOR.column_names()))
    notes: list[str] = field(default_factory=list)

    def options_for(self, ids: Sequence[str]) -> dict:
        """The chunk options (fit_presets' ``priors``, the candidates' ``field_geometry``) of
        the heliostats ``ids``."""
        return {"priors": {h: self.priors[h] for h in ids if h in self.priors},
                "field_geometry": {h: self.geometry[h] for h in ids if h in self.geometry}}


# ------------------------------------------------------------------------------------------------
# the sample's fits
# ------------------------------------------------------------------------------------------------
def _sample_task(task) -> list[list[CoarseFit]]:
    """One chunk of a group's sample: every preset of each heliostat (fit_presets)."""
    solver, hrows, rows, presets, options = task
    specs = [HeliostatSpec.from_row(pd.Series(h)) for h in hrows]
    trains = [MeasurementBatch.from_frame(r[r["split"] == "train"]) for r in rows]
    return fit_presets(specs, [nominal_parameters(pd.Series(h)) for h in hrows], trains, presets,
                       solver=solver, **options)


def _sample_of(helio: pd.DataFrame, rows_of: dict, members: Sequence[str]) -> list[str]:
    """A group's sample: its heliostats with training rows, most rows first (ties by id), at
    most :data:`SAMPLE_SIZE`."""
    n_train = {h: int((rows_of[h]["split"] == "train").sum()) for h in members if h in rows_of}
    ranked = sorted((h for h, n in n_train.items() if n > 0), key=lambda h: (-n_train[h], h))
    return ranked[:SAMPLE_SIZE]


def _fit_samples(helio, rows_of, samples: dict, presets, priors, *, solver, options, batch_size,
                 workers, scheduler, dask_address) -> dict:
    """heliostat -> its fits (one per preset) of every group's sample, under ``priors``."""
    tasks, order = [], []
    for key in sorted(samples):
        ids = samples[key]
        step = 1 if solver == "scipy" else batch_size
        for i in range(0, len(ids), step):
            chunk = ids[i:i + step]
            opts = dict(options, priors={h: priors[h] for h in chunk if h in priors})
            tasks.append((solver, [helio.loc[h].to_dict() for h in chunk],
                          [rows_of[h] for h in chunk], presets, opts))
            order.append(chunk)
    results = map_tasks(_sample_task, tasks, workers=workers, scheduler=scheduler,
                        dask_address=dask_address) if tasks else []
    return {h: fits for chunk, res in zip(order, results) for h, fits in zip(chunk, res)}


def _position(hrow) -> np.ndarray:
    return np.array([float(hrow["heliostat_e_m"]), float(hrow["heliostat_n_m"])])


# ------------------------------------------------------------------------------------------------
# the plan
# ------------------------------------------------------------------------------------------------
def _groups(helio: pd.DataFrame) -> dict[tuple, list[str]]:
    out: dict[tuple, list[str]] = {}
    for hid, hrow in helio.iterrows():
        out.setdefault(group_key(hrow), []).append(str(hid))
    return out


def _estimate(helio, rows_of, groups, presets, *, spatial: bool, fit_sample: Callable
              ) -> tuple[dict, list[str]]:
    """(group -> preset -> GroupPrior, notes) from :data:`PRIOR_ROUNDS` rounds of sample fits."""
    samples = {key: _sample_of(helio, rows_of, members) for key, members in groups.items()}
    samples = {k: v for k, v in samples.items() if len(v) > 1}
    priors: dict = {}
    estimates: dict = {}
    for round_ in range(PRIOR_ROUNDS):
        fits = fit_sample(samples, priors)
        estimates = {}
        for key, ids in samples.items():
            pos = {h: _position(helio.loc[h]) for h in groups[key]}
            for j, preset in enumerate(presets):
                sample = FitSample.of(ids, [fits[h][j] for h in ids], [pos[h] for h in ids])
                estimates.setdefault(key, {})[preset] = GroupPrior.estimate(
                    sample, posterior=round_ > 0, spatial=spatial, queries=pos)
        priors = _heliostat_priors(helio, estimates)
    notes = []
    for key, members in groups.items():
        best = max((int(g.whole.n.max()) for g in estimates.get(key, {}).values()), default=0)
        if not any(g.whole.used.any() for g in estimates.get(key, {}).values()):
            notes.append(f"no field prior for the {len(members)} {_group_text(key)}: "
                         f"{best} well-determined heliostat(s) per parameter, fewer than "
                         f"{MIN_HELIOSTATS}; they are fitted with the default prior")
    return estimates, notes


def _group_text(key: tuple) -> str:
    kt, at, source = key
    what = "with properties files" if source == "properties" else "with the default geometry"
    return f"heliostats of type {kt}/{at} {what}"


def _heliostat_priors(helio: pd.DataFrame, estimates: dict) -> dict[str, dict[str, tuple]]:
    """heliostat -> preset -> (mean (28,), sigma (28,)) from the groups' estimates."""
    out: dict[str, dict[str, tuple]] = {}
    for hid, hrow in helio.iterrows():
        nominal = nominal_parameters(hrow).numpy()
        for preset, g in estimates.get(group_key(hrow), {}).items():
            p = g.prior_of(str(hid), nominal)
            if p is not None:
                out.setdefault(str(hid), {})[preset] = p
    return out


def _table(estimates: dict) -> pd.DataFrame:
    """field_prior.parquet's rows of the groups' whole-sample priors (those with one)."""
    frames = []
    for (kt, at, source), by_preset in sorted(estimates.items()):
        for preset, g in by_preset.items():
            if g.whole.used.any():
                frames.append(g.table().assign(kinematic_type=kt, actuator_type=at,
                                               geometry_source=source, preset=preset))
    if not frames:
        return pd.DataFrame(columns=FIELD_PRIOR.column_names())
    return pd.concat(frames, ignore_index=True).assign(
        expected_error_mrad=np.nan, nominal_error_mrad=np.nan, n_evaluated=0)


def _from_table(table: pd.DataFrame, groups: dict, presets, helio, other: str
                ) -> tuple[dict, list[str]]:
    """(group -> preset -> GroupPrior, notes) from another work directory's field_prior.parquet;
    what does not match this run (a group or preset it lacks, parameters that are not the
    preset's) is said and fitted with the default prior."""
    have = sorted({tuple(k) for k in table[["kinematic_type", "actuator_type",
                                             "geometry_source"]].itertuples(index=False)})
    estimates, notes = {}, []
    for key, members in sorted(groups.items()):
        rows = table[(table["kinematic_type"] == key[0]) & (table["actuator_type"] == key[1])
                     & (table["geometry_source"] == key[2])]
        if rows.empty:
            notes.append(f"the prior of {other} has no {_group_text(key)} (it has "
                         f"{', '.join('/'.join(k) for k in have) or 'no group'}); these "
                         f"{len(members)} heliostats are fitted without a field prior")
            continue
        for preset in presets:
            est, why = _estimate_from_rows(rows[rows["preset"] == preset], preset, key)
            if est is None:
                notes.append(f"the prior of {other} for {_group_text(key)} {why}; {preset} is "
                             "fitted with the default prior")
                continue
            estimates.setdefault(key, {})[preset] = GroupPrior(est, {}, {})
    return estimates, notes


def _estimate_from_rows(rows: pd.DataFrame, preset: str, key: tuple
                        ) -> tuple[PriorEstimate | None, str]:
    """A field_prior.parquet group's rows of one preset as an estimate, or (None, why not)."""
    if rows.empty:
        return None, f"has no preset {preset}"
    by_name = rows.set_index("parameter")
    names = list(by_name.index)
    if sorted(names) != sorted(PARAMETER_NAMES) or len(set(names)) != len(names):
        odd = sorted(set(names) ^ set(PARAMETER_NAMES))[:3]
        return None, (f"of preset {preset} does not list the 28 parameters once each "
                      f"(e.g. {', '.join(odd) or 'a repeated name'})")
    by_name = by_name.loc[list(PARAMETER_NAMES)]
    sigma = by_name["scale"].to_numpy(float)
    mean = by_name["mean"].to_numpy(float)
    free = preset_mask(preset, key[1], key[0]).numpy()
    bad = [n for n, s, f in zip(PARAMETER_NAMES, sigma, free) if np.isfinite(s) and not f]
    if bad:
        return None, (f"gives preset {preset} a prior on {', '.join(bad[:3])}, which the preset "
                      f"does not fit on type {key[0]}/{key[1]}")
    ok = np.isfinite(sigma) & (sigma > 0) & np.isfinite(mean)
    if not ok.any():
        return None, f"has no parameter with a scale for preset {preset}"
    n = by_name["n_heliostats"].to_numpy(np.int64)
    noise = by_name["noise_mrad"].to_numpy(float)[ok] if "noise_mrad" in by_name else []
    noise = float(np.nanmedian(noise)) if np.isfinite(noise).any() else math.nan
    return PriorEstimate(np.where(ok, mean, 0.0), np.where(ok, sigma, np.nan),
                         np.where(ok, sigma, np.nan), n, noise_mrad=noise), ""


def plan_field_prior(helio: pd.DataFrame, rows_of: dict, presets: Sequence[str], *, mode: str,
                     prior_from: str | Path | None, solver: str, options: dict, batch_size: int,
                     workers=1, scheduler: str = "local", dask_address=None) -> PriorPlan:
    """The field prior of a fit-coarse run (module docstring).

    Parameters
    ----------
    helio : heliostats.parquet indexed by id (every heliostat of the work directory: a
        heliostat without training rows gets the field-prior geometry).
    rows_of : heliostat -> its rows with the split labels (those with training rows).
    presets : the run's presets, smallest first.
    mode : one of :data:`PRIOR_MODES`.
    prior_from : another work directory whose field_prior.parquet to use (not with
        ``field+spatial``, which needs this field's fits).
    solver, options, batch_size, workers, scheduler, dask_address : as the stage's fits.
    """
    plan = PriorPlan(mode, None if prior_from is None else str(prior_from))
    if mode == CoarsePrior.none.value:
        if prior_from is not None:
            raise ParameterError("fit-coarse --prior-from needs --prior field (it was --prior "
                                 "none)")
        return plan
    groups = _groups(helio)
    if prior_from is not None:
        if mode != CoarsePrior.field.value:
            raise ParameterError(f"fit-coarse --prior-from uses another field's prior as it is; "
                                 f"--prior {mode} needs this field's fits: use --prior field")
        table = _read_other(prior_from)
        estimates, plan.notes = _from_table(table, groups, presets, helio, str(prior_from))
    else:
        def fit_sample(samples, priors):
            return _fit_samples(helio, rows_of, samples, presets, priors, solver=solver,
                                options=options, batch_size=batch_size, workers=workers,
                                scheduler=scheduler, dask_address=dask_address)

        estimates, plan.notes = _estimate(helio, rows_of, groups, presets,
                                          spatial=mode == CoarsePrior.field_spatial.value,
                                          fit_sample=fit_sample)
    plan.priors = _heliostat_priors(helio, estimates)
    plan.table = _table(estimates)
    first = presets[0]
    for hid, by_preset in plan.priors.items():
        if first in by_preset:
            plan.geometry[hid] = (field_prior_name(first), by_preset[first][0])
    return plan


def _read_other(prior_from) -> pd.DataFrame:
    """The field_prior.parquet of another work directory (through its manifest)."""
    other = Path(prior_from)
    if not other.is_dir():
        raise StageInputError(f"--prior-from {other}: no such work directory; give the folder "
                              "of a fit-coarse run with a field prior")
    # read outside this run's transaction (the other work directory's own inputs are not this
    # run's), then recorded as a source of this run: its provenance names the file and its hash
    txn = ACTIVE_TRANSACTION.get()
    token = ACTIVE_TRANSACTION.set(None)
    try:
        table = read_artifact(other, FIELD_PRIOR)
    finally:
        ACTIVE_TRANSACTION.reset(token)
    if txn is not None:
        path = artifact_path(other, FIELD_PRIOR)
        txn.add_source("prior_from", path, hashlib.sha256(path.read_bytes()).hexdigest())
    if table.empty:
        raise StageInputError(f"--prior-from {other}: its field_prior.parquet holds no prior "
                              "(its fit-coarse ran with --prior none, or no group had enough "
                              "well-determined heliostats)")
    return table


# ------------------------------------------------------------------------------------------------
# the field-prior geometry as a model
# ------------------------------------------------------------------------------------------------
def field_prior_fit(name: str, params: np.ndarray, nominal: torch.Tensor, spec: HeliostatSpec,
                    status: str = "the field prior's geometry (not fitted)") -> CoarseFit:
    """The field-prior geometry as a :class:`CoarseFit` candidate: no free parameter, so no
    standard error; its ``free`` mask is its preset's (the parameters the prior moves)."""
    preset = name.split("+")[0]
    free = preset_mask(preset, spec.actuator_type, spec.kinematic_type).numpy()
    return CoarseFit(name, torch.as_tensor(params, dtype=torch.float64), nominal.to(torch.float64),
                     free, np.full(len(PARAMETER_NAMES), np.nan), np.zeros(len(PARAMETER_NAMES), bool),
                     0, float("nan"), float("nan"), status, [], 0.0)


def with_field_prior(inp, fits: list[CoarseFit], time_fits: list | None,
                      field_geometry: dict | None) -> tuple[list, list | None]:
    """A heliostat's fits and time-split fits with its field-prior geometry first (a candidate
    of the selection, so no fit worse on validation than the field's typical geometry is
    selected; issue 34). The geometry does not depend on the heliostat's rows: it is its own
    time-split "fit"."""
    if not field_geometry or inp.hid not in field_geometry:
        return list(fits), time_fits
    name, params = field_geometry[inp.hid]
    geometry = field_prior_fit(name, params, inp.nominal, inp.spec)
    return [geometry] + list(fits), (None if time_fits is None else [geometry] + list(time_fits))


def zero_row_outputs(helio: pd.DataFrame, plan: PriorPlan, with_rows: set[str],
                     heliostats: Sequence[str] | None) -> tuple[list[dict], list[str]]:
    """coarse_params rows of the heliostats without training rows that get the field-prior
    geometry (selected, ``n_train`` 0), and their ids."""
    rows, ids = [], []
    wanted = None if heliostats is None else set(heliostats)
    for hid, hrow in helio.iterrows():
        hid = str(hid)
        if hid in with_rows or hid not in plan.geometry or (wanted and hid not in wanted):
            continue
        name, params = plan.geometry[hid]
        nominal = nominal_parameters(hrow).numpy()
        free = preset_mask(name.split("+")[0], str(hrow["actuator_type"]),
                           str(hrow["kinematic_type"])).numpy()
        status = "no training rows: the field prior's geometry of its group (not fitted)"
        for i, pname in enumerate(PARAMETER_NAMES):
            rows.append({
                "heliostat_id": hid, "preset": name, "selected": True, "parameter_index": i,
                "parameter": pname, "unit": _unit(pname), "nominal": float(nominal[i]),
                "fitted": float(params[i]), "std_error": float("nan"), "free": bool(free[i]),
                "determined": False, "fit_iterations": 0, "fit_cost": float("nan"),
                "fit_condition_number": float("nan"), "fit_status": status,
                "fit_implausible": "", "fit_degenerate": "no training rows", "n_train": 0,
                "train_error_mrad": float("nan"), "val_error_mrad": float("nan"),
                "test_error_mrad": float("nan"), "time_fitted": float("nan"),
                "time_val_error_mrad": float("nan"), "time_test_error_mrad": float("nan")})
        ids.append(hid)
    return rows, ids


def _unit(name: str) -> str:
    from ..physics.parameters import PARAMETER_UNITS

    return PARAMETER_UNITS[name]


def prior_columns(fit: CoarseFit, i: int) -> dict:
    """A fit's coarse_params columns of how much parameter ``i`` leans on its prior, and the
    noise the prior was weighed against (:func:`attach_prior_columns` blanks them where the fit
    had no field prior)."""
    share = fit.prior_shrinkage
    return {"prior_shrinkage": np.nan if share is None else float(share[i]),
            "own_noise_mrad": fit.own_noise_mrad, "prior_noise_mrad": fit.prior_noise_mrad}


def attach_prior_columns(params: pd.DataFrame, plan: PriorPlan) -> pd.DataFrame:
    """coarse_params with ``prior_mean`` and ``prior_sigma``: the field prior each preset's fit
    was given, on the rows of the parameters it covers (missing elsewhere, and there
    ``prior_shrinkage`` too), and ``prior_field_noise_mrad``: the field's noise the entries
    that are the field's were first weighed against (missing on the default prior's; with
    ``prior_mean`` and ``prior_sigma`` it gives the prior back,
    :func:`~.study_prior.heliostat_priors`); ``own_noise_mrad`` and ``prior_noise_mrad`` on
    the rows of fits with a field prior (missing elsewhere: a regime-aware candidate or the field-prior geometry
    is not such a fit)."""
    mean = np.full(len(params), np.nan)
    sigma = np.full(len(params), np.nan)
    field_noise = np.full(len(params), np.nan)
    if plan.priors and len(params):
        hid = params["heliostat_id"].to_numpy()
        preset = params["preset"].to_numpy()
        index = params["parameter_index"].to_numpy()
        for r in range(len(params)):
            p = plan.priors.get(hid[r], {}).get(preset[r])
            if p is not None:
                mean[r], sigma[r] = p[0][index[r]], p[1][index[r]]
                if isinstance(p, HeliostatPrior) and p.field is not None and p.field[index[r]]:
                    field_noise[r] = p.noise[index[r]]
    out = params.assign(prior_mean=mean, prior_sigma=sigma, prior_field_noise_mrad=field_noise)
    for column in ("prior_shrinkage", "own_noise_mrad", "prior_noise_mrad"):
        if column not in out.columns:  # rows without a fit (zero-row heliostats) only
            out[column] = np.nan
    has = out["prior_sigma"].notna()
    fitted_under = has.groupby([out["heliostat_id"], out["preset"]], sort=False).transform("any")
    out.loc[~fitted_under.to_numpy(bool), ["own_noise_mrad", "prior_noise_mrad"]] = np.nan
    default = out["prior_sigma"].isna() | ~out["free"].to_numpy(bool)
    out.loc[default, ["prior_mean", "prior_sigma", "prior_shrinkage",
                      "prior_field_noise_mrad"]] = np.nan
    return out


def finish_table(plan: PriorPlan, helio: pd.DataFrame, params: pd.DataFrame,
                 preds: pd.DataFrame) -> pd.DataFrame:
    """field_prior.parquet with each group's expected error: the median over its heliostats with
    test rows of the field-prior geometry's mean test error (each heliostat's own from the other
    heliostats' prior), and the same median of the nominal geometry. Read from the run's
    coarse_params and coarse_predictions as written (an incremental run's kept heliostats
    count as a full run's)."""
    table = plan.table.copy()
    if table.empty:
        return table
    nominal_test = _nominal_test_error(preds)
    per_group: dict = {}
    for hid, got in params.groupby("heliostat_id", sort=True):
        name = plan.geometry.get(str(hid), (None,))[0]
        test = got.loc[got["preset"] == name, "test_error_mrad"].to_numpy(float)[:1]
        if not len(test) or not math.isfinite(test[0]):
            continue
        per_group.setdefault(group_key(helio.loc[hid]), []).append(
            (test[0], nominal_test.get(str(hid), float("nan"))))
    for key, values in per_group.items():
        sel = ((table["kinematic_type"] == key[0]) & (table["actuator_type"] == key[1])
               & (table["geometry_source"] == key[2]))
        arr = np.array(values, float)
        table.loc[sel, "expected_error_mrad"] = float(np.median(arr[:, 0]))
        table.loc[sel, "nominal_error_mrad"] = float(np.nanmedian(arr[:, 1]))
        table.loc[sel, "n_evaluated"] = len(values)
    return table


def _nominal_test_error(preds: pd.DataFrame) -> dict[str, float]:
    """heliostat -> the nominal geometry's mean error_mrad on its test rows (coarse_predictions)."""
    test = preds[(preds["model"] == "nominal") & (preds["split"] == "test")]
    return {str(h): float(v) for h, v in test.groupby("heliostat_id")["error_mrad"].mean().items()}


def prior_frame(plan: PriorPlan, ids) -> pd.DataFrame:
    """One row per heliostat of ``ids``, preset and parameter with the prior (mean, sigma) its fit
    is given: the part of a heliostat's inputs that comes from the field (the incremental plan
    hashes it with the heliostat's own rows, so a moved prior fits it again); ``sigma`` as the
    fit weighs it (over the measurements' noise the prior is weighed against, in mrad)."""
    rows = [(hid, name, i, float(mean[i]), float(sigma[i] / (rest[0][i] if rest else 1.0)))
            for hid in sorted(ids) for name, (mean, sigma, *rest) in
            sorted(plan.priors.get(hid, {}).items()) for i in range(len(mean))]
    return pd.DataFrame(rows, columns=["heliostat_id", "preset", "parameter_index", "mean",
                                       "sigma"])


def with_deviations(params: pd.DataFrame) -> pd.DataFrame:
    """coarse_params with ``deviation``: each row's fitted minus nominal value in
    field_prior.parquet's units (angles wrapped, increments relative to the nominal; the
    report's field-prior page draws it against the prior)."""
    out = params.copy()
    dev = np.full(len(out), np.nan)
    for _, idx in out.groupby(["heliostat_id", "preset"], sort=False).indices.items():
        g = out.iloc[idx]
        at = g["parameter_index"].to_numpy(int)
        fitted, nominal = np.zeros(len(PARAMETER_NAMES)), np.zeros(len(PARAMETER_NAMES))
        fitted[at], nominal[at] = g["fitted"].to_numpy(float), g["nominal"].to_numpy(float)
        dev[idx] = deviation(fitted, nominal)[at]
    out["deviation"] = dev
    return out


def heliostat_groups(helio: pd.DataFrame) -> dict[str, tuple[str, str, str]]:
    """heliostat -> its field-prior group (heliostats.parquet rows, column ``heliostat_id``)."""
    return {str(r["heliostat_id"]): group_key(r) for _, r in helio.iterrows()}


def summary_of(plan: PriorPlan, table: pd.DataFrame, zero_rows: Sequence[str]) -> dict:
    """The stage summary's ``field_prior`` entry."""
    groups = []
    for key, g in table.groupby(["kinematic_type", "actuator_type", "geometry_source"], sort=True):
        groups.append({"group": "/".join(key), "presets": sorted(g["preset"].unique()),
                       "parameters_with_prior": int(g["scale"].notna().sum()),
                       "max_heliostats": int(g["n_heliostats"].max()),
                       "expected_error_mrad": _mean(g["expected_error_mrad"].to_numpy(float)),
                       "nominal_error_mrad": _mean(g["nominal_error_mrad"].to_numpy(float))})
    return {"mode": plan.mode, "prior_from": plan.prior_from, "groups": groups,
            "zero_row_heliostats": list(zero_rows), "notes": list(plan.notes)}


def field_prior_note(workdir, hrow, model: str) -> str | None:
    """What ``aim`` says of a heliostat whose selected model is its group's field-prior
    geometry (None for any other model): that it has no fit of its own, and the error measured
    on heliostats like it (field_prior.parquet ``expected_error_mrad``, where known)."""
    from ..artifacts.store import artifact_present

    if not is_field_prior(model):
        return None
    hid = str(hrow["heliostat_id"])
    text = (f"{hid} has no fit of its own (no training rows): it aims with the field-prior "
            f"geometry of its group ({model}, the nominal geometry moved by the field's typical "
            "deviations)")
    if artifact_present(workdir, FIELD_PRIOR):
        table = read_artifact(workdir, FIELD_PRIOR)
        kt, at, source = group_key(hrow)
        mine = table[(table["kinematic_type"] == kt) & (table["actuator_type"] == at)
                     & (table["geometry_source"] == source)]
        if len(mine) and math.isfinite(float(mine["expected_error_mrad"].iloc[0])):
            r = mine.iloc[0]
            text += (f"; on the test rows of {int(r['n_evaluated'])} heliostats like it that "
                     f"geometry is off by {float(r['expected_error_mrad']):.3g} mrad (median; "
                     f"nominal geometry {float(r['nominal_error_mrad']):.3g} mrad)")
    return text + "; calibrate it to get its own fit"
