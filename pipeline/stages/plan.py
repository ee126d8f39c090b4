"""``plan``: which heliostats to measure next, and when (docs/plan.md).

For every heliostat the coarse fit's posterior covariance (:mod:`..models.uncertainty`) on the
rows it rests on, the year's information matrix of its aims at the site, and candidate rows: each
of its targets at every slot of the coming days (:mod:`..models.schedule`), or with
``--from-existing`` its rows already measured in those days. The field's budget goes greedily to
the row of highest expected gain (:mod:`..models.design`), updating that heliostat's covariance
after each pick. Writes ``plan.parquet`` and ``plan.csv`` in one transaction.
"""

from __future__ import annotations

import logging
import math
import pickle
from collections import defaultdict
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from ..artifacts.manifests import current_transaction
from ..artifacts.schemas import (COARSE_PARAMS, HELIOSTATS, MEASUREMENTS, PLAN, REGIMES, SPLIT)
from ..artifacts.store import artifact_present, check_fresh, read_artifact, write_artifact
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir
from ..errors import InputError, ParameterError, StageInputError, check_float, check_int
from ..models.coarse import MeasurementBatch
from ..models.design import aim_rows, heliostat_designs, year_variance_mrad2
from ..models.schedule import (GridCandidates, Limits, RowCandidates, greedy_schedule, slot_grid,
                               year_sun_grid)
from ..models.uncertainty import aim_jacobian, covariance_after
from ..runtime.parallel import map_tasks, shared_pool, warm_up_stage
from ..runtime.process_state import restores_process_state
from ..vocabulary import PLAN_MIN_ELEVATION_DEG
from .fit_coarse import load_selected_parameters, load_split_labels
from .plan_inputs import (PriorScale, default_prior_scale, log_per_day, log_spacing_s,
                          planned_heliostats, plant_site, solar_days)

__all__ = ["run_plan", "MIN_ELEVATION_DEG", "NODE_MINUTES", "YEAR_EVERY_DAYS",
           "YEAR_EVERY_MINUTES", "MAX_DAYS", "MAX_DAYS_EXISTING", "MIN_NOISE_DOF"]

log = logging.getLogger("heliocal.plan")

#: Lowest sun elevation of a planned measurement and of the year's aims [deg] (the simulator's
#: calibration floor; the Jülich log reaches down to 4.8 deg).
MIN_ELEVATION_DEG = PLAN_MIN_ELEVATION_DEG

#: Candidate Jacobians are exact every this many minutes and interpolated between (docs/plan.md:
#: at 30 min the gains differ from exact ones by < 0.4 % of the largest).
NODE_MINUTES = 30

#: The year's aims: every 15th day, every 30 minutes (the expected year-round error is within
#: 1 % of a grid of every day and 10 minutes, docs/plan.md).
YEAR_EVERY_DAYS, YEAR_EVERY_MINUTES = 15, 30

#: Longest plan [days]: a plan is meant to be made again as its rows come in (its candidates
#: cost memory per day). With --from-existing a window may cover the logs' whole history.
MAX_DAYS, MAX_DAYS_EXISTING = 62, 3660

#: Heliostats per batched design task.
CHUNK = 64

#: A heliostat's own noise scale needs this many degrees of freedom (2 N - P) of its residuals;
#: with fewer (a fit of P parameters on about P / 2 rows nearly interpolates them) it takes the
#: field's median: the noise is mostly the camera-target system's, shared by the field.
MIN_NOISE_DOF = 10

_FUNC = "plan"


def _check_options(start, days, per_day, budget, max_per_heliostat, spacing_minutes,
                   min_elevation_deg, seed, from_existing):
    try:
        day = pd.Timestamp(start)
    except (ValueError, TypeError):
        day = None
    if day is None or day is pd.NaT or day != day.normalize():
        raise ParameterError(f"The 'start' parameter of {_FUNC} must be a date like 2024-06-01. "
                             f"Got {start!r} instead.")
    days = check_int(days, "days", _FUNC, 1, MAX_DAYS_EXISTING if from_existing else MAX_DAYS)
    per_day = None if per_day is None else check_int(per_day, "per_day", _FUNC, 1)
    budget = None if budget is None else check_int(budget, "budget", _FUNC, 1)
    if max_per_heliostat is not None:
        max_per_heliostat = check_int(max_per_heliostat, "max_per_heliostat", _FUNC, 1)
    if spacing_minutes is not None:
        spacing_minutes = check_float(spacing_minutes, "spacing_minutes", _FUNC, 0.0, 1440.0,
                                      low_inclusive=False)
    min_elevation_deg = check_float(min_elevation_deg, "min_elevation_deg", _FUNC, 0.0, 89.0)
    seed = check_int(seed, "seed", _FUNC, 0)
    return (str(day.date()), days, per_day, budget, max_per_heliostat, spacing_minutes,
            min_elevation_deg, seed)


def _read_heliostats(workdir: Path, heliostats: Sequence[str] | None) -> pd.DataFrame:
    """heliostats.parquet's rows of the heliostats to plan (all, or the ones asked for)."""
    helio = read_artifact(workdir, HELIOSTATS)
    if heliostats:
        known = set(helio["heliostat_id"])
        unknown = [h for h in heliostats if h not in known]
        if unknown:
            raise InputError(f"heliostat {unknown[0]!r} is not in {workdir}/heliostats.parquet "
                             f"({len(known)} heliostats; `heliocal info {workdir}` lists them)")
        helio = helio[helio["heliostat_id"].isin(set(heliostats))]
    return helio.reset_index(drop=True)


def _check_daylight(site, start: str, days: int, min_elevation_deg: float) -> None:
    """One clear error when the sun never rises above the minimum elevation in the plan."""
    if not len(slot_grid(site, start, days, 600, 1, min_elevation_deg)):
        raise InputError(f"no daylight in the plan: the sun stays below {min_elevation_deg:g} "
                         f"deg at the site ({site[0]:.3f}, {site[1]:.3f}) for {days} days from "
                         f"{start}; choose other dates or a lower --min-elevation")


def _read_fits(workdir: Path, helio: pd.DataFrame):
    """Measurements (with split labels), the selected coarse fits and the regimes."""
    if not artifact_present(workdir, COARSE_PARAMS):
        raise StageInputError(f"{workdir} has no coarse fit (coarse_params.parquet): run "
                              f"`heliocal fit-coarse --workdir {workdir}` first")
    upstream = {"measurements": MEASUREMENTS}
    if artifact_present(workdir, SPLIT):
        upstream["split"] = SPLIT
    check_fresh(workdir, COARSE_PARAMS, upstream)
    ids = list(helio["heliostat_id"])
    meas = read_artifact(workdir, MEASUREMENTS, heliostats=ids)
    meas = meas.sort_values("heliostat_id", kind="mergesort").reset_index(drop=True)
    meas["split"] = load_split_labels(workdir, meas).to_numpy()
    selected = load_selected_parameters(workdir, ids)
    regimes = read_artifact(workdir, REGIMES, heliostats=ids) if artifact_present(workdir, REGIMES) else None
    return meas, selected, regimes


def _pace(meas, site, n_heliostats, spacing_minutes, per_day, budget, days, max_per_heliostat):
    """(spacing [s], its source, the limits, per-day source): the options, else the logs'."""
    if spacing_minutes is not None:
        spacing_s, spacing_source = max(int(round(spacing_minutes * 60)), 1), "given with --spacing"
    else:
        spacing_s, spacing_source = log_spacing_s(meas)
    per_day_source = "given"
    if per_day is None and budget is None:
        per_day, per_day_source = log_per_day(meas, site[1], n_heliostats)
    total = min(x for x in (budget, per_day * days if per_day else None) if x is not None)
    return spacing_s, spacing_source, Limits(total, days, per_day, max_per_heliostat), per_day_source


def _design_task(task: bytes) -> list:
    """One chunk's designs (a task for map_tasks: the pickled (items, year sun, node sun,
    candidate rows)); with candidate rows also their data Jacobians (R, 3, P). The task is
    pickled by value (plain pickle) because torch sends the tensors of a task through shared
    memory, one file descriptor each, and thousands of heliostats' tensors exhaust them."""
    items, year_sun, node_sun, candidates = pickle.loads(task)
    designs = heliostat_designs(items, year_sun, node_sun)
    if candidates is None:
        return [(d, None) for d in designs]
    out = []
    for item, d, rows in zip(items, designs, candidates):
        b = MeasurementBatch.from_frame(rows)
        j = aim_jacobian(item.spec, item.params, d.covariance.free_idx, b.steps, b.sun,
                         b.focal_spot) if len(b) else np.zeros((0, 3, len(d.covariance.free_idx)))
        out.append((d, j))
    return out


def _chunk_tasks(planned, indices, year_sun, node_sun, rows_mode: bool) -> tuple[list, list]:
    """Tasks of heliostats ``indices``: one kinematic and actuator type and one free set each."""
    groups = defaultdict(list)
    for k in indices:
        it = planned[k].item
        groups[(it.spec.kinematic_type, it.spec.actuator_type,
                tuple(np.asarray(it.free, bool)))].append(k)
    tasks, order = [], []
    for key in sorted(groups, key=str):
        members = groups[key]
        for i in range(0, len(members), CHUNK):
            part = members[i:i + CHUNK]
            tasks.append(pickle.dumps(
                ([planned[k].item for k in part], year_sun, node_sun,
                 [planned[k].candidates for k in part] if rows_mode else None),
                protocol=pickle.HIGHEST_PROTOCOL))
            order.append(part)
    return tasks, order


def _noise_groups(planned) -> tuple[list[int], list[int]]:
    """(heliostats whose own rows give the noise scale, the others, which take the first
    group's median): own when the residuals leave at least :data:`MIN_NOISE_DOF` degrees of
    freedom; when none does, those with at least one, else every heliostat with rows."""
    dof = [p.noise_dof for p in planned]
    for least in (MIN_NOISE_DOF, 1, -math.inf):
        own = [k for k, d in enumerate(dof) if d is not None and d >= least]
        if own:
            mine = set(own)
            return own, [k for k in range(len(planned)) if k not in mine]
    return [], list(range(len(planned)))


def _designs(planned, year_sun, node_sun, rows_mode: bool, workers) -> tuple[list, list, float]:
    """Every heliostat's design (and candidate row Jacobians): those with a noise scale of
    their own first (:func:`_noise_groups`), then the others with the field's median."""
    designs, row_jacs = [None] * len(planned), [None] * len(planned)
    own, rest = _noise_groups(planned)

    def run(indices):
        tasks, order = _chunk_tasks(planned, indices, year_sun, node_sun, rows_mode)
        for part, results in zip(order, map_tasks(_design_task, tasks, workers=workers)):
            for k, (d, j) in zip(part, results):
                designs[k], row_jacs[k] = d, j

    run(own)
    noise = float(np.median([designs[k].covariance.noise_mrad for k in own])) if own else math.nan
    if rest:
        if not math.isfinite(noise):
            raise StageInputError("no heliostat has a coarse fit with training rows to take the "
                                  "measurement noise from: run `heliocal fit-coarse` on a split "
                                  "with training rows first")
        for k in rest:
            planned[k].item.noise_mrad = noise
        run(rest)
    return designs, row_jacs, noise


def _exact_rows(planned, designs, picks, grid) -> dict:
    """Grid picks at their exact times: per pick index (steps (2,), Jacobian (3, P)), batched per
    kinematic type and free set (one inverse kinematics and Jacobian each)."""
    by_h = defaultdict(list)
    for i, p in enumerate(picks):
        by_h[p.heliostat].append(i)
    groups = defaultdict(list)
    for h in by_h:
        it = planned[h].item
        groups[(it.spec.kinematic_type, it.spec.actuator_type,
                tuple(np.asarray(it.free, bool)))].append(h)
    out = {}
    for members in groups.values():
        for c in range(0, len(members), CHUNK):
            part = members[c:c + CHUNK]
            width = max(len(by_h[h]) for h in part)
            sun = np.zeros((len(part), width, 3))
            aims = np.zeros((len(part), width, 3))
            for r, h in enumerate(part):
                idx = by_h[h] + [by_h[h][0]] * (width - len(by_h[h]))      # pad with the first
                sun[r] = grid.sun[[picks[i].slot for i in idx]]
                aims[r] = planned[h].item.target_points[[picks[i].target for i in idx]]
            steps, jac = aim_rows([planned[h].item for h in part], sun, aims)
            for r, h in enumerate(part):
                for col, i in enumerate(by_h[h]):
                    out[i] = (steps[r, col], jac[r, col])
    return out


def _plan_rows(planned, designs, picks, exact, grid) -> tuple[pd.DataFrame, list, int]:
    """plan.parquet's rows (gains again from exact Jacobians, per heliostat in rank order), the
    covariances after the plan and the number of picks dropped as out of reach at their exact
    time."""
    covs = [d.covariance for d in designs]
    rows, dropped = [], 0
    for i, p in enumerate(picks):
        h = p.heliostat
        if grid is not None:
            steps, jac = exact[i]
            t, day = grid.time[p.slot], p.day
            az, el = grid.azimuth_deg[p.slot], grid.elevation_deg[p.slot]
            target, mid = planned[h].targets[p.target], None
        else:
            r = planned[h].candidates.iloc[p.slot]
            steps, jac = r[["axis_1_steps", "axis_2_steps"]].to_numpy(float), p.jacobian
            t, day, az, el = r["timestamp"], int(r["day"]), r["sun_azimuth_deg"], r["sun_elevation_deg"]
            target, mid = r["target_name"], str(r["measurement_id"])
        if not np.isfinite(jac).all():
            dropped += 1
            continue
        before = year_variance_mrad2(covs[h], designs[h].information)
        covs[h] = covariance_after(covs[h], np.asarray(jac, float)[None])
        after = year_variance_mrad2(covs[h], designs[h].information)
        rows.append({"rank": len(rows) + 1, "heliostat_id": planned[h].item.heliostat_id,
                     "time_utc": pd.Timestamp(t), "day": int(day), "target": target,
                     "sun_azimuth_deg": float(az), "sun_elevation_deg": float(el),
                     "axis_1_steps": float(steps[0]), "axis_2_steps": float(steps[1]),
                     "expected_gain_mrad2": before - after,
                     "expected_error_before_mrad": math.sqrt(max(before, 0.0)),
                     "expected_error_after_mrad": math.sqrt(max(after, 0.0)),
                     "coarse_model": planned[h].model, "measurement_id": mid})
    return pd.DataFrame(rows, columns=PLAN.column_names()), covs, dropped


def _random_baseline(planned, designs, counts, grid, row_jacs, seed: int) -> np.ndarray:
    """Expected year-round variance [mrad^2] of each heliostat after as many rows as the plan
    gives it at random: random targets and slots (or random candidate rows), seeded."""
    rng = np.random.default_rng(seed)
    out = np.array([d.variance_mrad2 for d in designs])
    for h in np.flatnonzero(counts):
        d = designs[h]
        if grid is None:
            pool = row_jacs[h]
            j = pool[rng.choice(len(pool), size=min(counts[h], len(pool)), replace=False)]
        else:
            t = rng.integers(0, len(planned[h].targets), size=counts[h])
            s = rng.integers(0, len(grid), size=counts[h])
            j = np.stack([grid.interpolate(d.node_jacobian[a], np.array([b]))[0]
                          for a, b in zip(t, s)])
        j = j[np.isfinite(j).all(axis=(1, 2))]
        out[h] = year_variance_mrad2(covariance_after(d.covariance, j), d.information)
    return out


def _csv_bytes(plan: pd.DataFrame) -> bytes:
    """plan.csv: the plan in time order (ISO 8601 UTC), one row per measurement."""
    cols = ["time_utc", "heliostat_id", "target", "axis_1_steps", "axis_2_steps",
            "sun_azimuth_deg", "sun_elevation_deg", "expected_gain_mrad2", "rank",
            "measurement_id"]
    out = plan.sort_values(["time_utc", "target", "rank"], kind="mergesort")[cols].copy()
    out["time_utc"] = pd.to_datetime(out["time_utc"], utc=True).dt.strftime("%Y-%m-%dT%H:%M:%SZ")
    return out.to_csv(index=False, float_format="%.6g", lineterminator="\n").encode("utf-8")


@locks_workdir("plan")
@stage_transaction("plan")
@restores_process_state
@shared_pool()
def run_plan(workdir: str | Path, *, start, days: int, per_day: int | None = None,
             budget: int | None = None, max_per_heliostat: int | None = None,
             from_existing: bool = False, spacing_minutes: float | None = None,
             min_elevation_deg: float = MIN_ELEVATION_DEG,
             heliostats: Sequence[str] | None = None, seed: int = 0, workers: int | None = 1,
             prior: PriorScale = default_prior_scale) -> dict:
    """The ``plan`` stage: choose the next measurements, write plan.parquet and plan.csv.

    Parameters
    ----------
    start : first (solar) day of the plan, a date like ``2024-06-01``.
    days : days in the plan [1, :data:`MAX_DAYS`] (with ``from_existing``
        :data:`MAX_DAYS_EXISTING`).
    per_day, budget : measurements per day and in all (both apply when both are given; neither:
        the logs' median per measurement day).
    max_per_heliostat : at most this many rows per heliostat (default: no limit).
    from_existing : choose among rows already measured in those days, not yet in the test set.
    spacing_minutes : least time between two measurements on one target [min] (default from the
        logs, :func:`.plan_inputs.log_spacing_s`; ignored with ``from_existing``: those rows were
        measured as they were).
    min_elevation_deg : lowest sun elevation of a planned row and of the year's aims [deg].
    heliostats : plan only these.
    seed : seed of the random baseline the summary compares the plan with.
    workers : processes of the batched design (results do not depend on it).
    prior : the prior's scale per heliostat (:data:`.plan_inputs.PriorScale`).
    """
    (start, days, per_day, budget, max_per_heliostat, spacing_minutes, min_elevation_deg,
     seed) = _check_options(start, days, per_day, budget, max_per_heliostat, spacing_minutes,
                            min_elevation_deg, seed, from_existing)
    warm_up_stage("plan", workers=workers)
    workdir = Path(workdir)
    helio = _read_heliostats(workdir, heliostats)
    site = plant_site(workdir, helio)
    if not from_existing:
        _check_daylight(site, start, days, min_elevation_deg)
    meas, selected, regimes = _read_fits(workdir, helio)
    spacing_s, spacing_source, limits, per_day_source = _pace(
        meas, site, len(helio), spacing_minutes, per_day, budget, days, max_per_heliostat)
    planned = planned_heliostats(
        helio, meas, selected, regimes, prior, window_start=start if from_existing else None,
        window_days=solar_days(meas["timestamp"], start, site[1]) if from_existing else None,
        days=days)
    grid = None
    if from_existing:
        if not any(p.candidates is not None and len(p.candidates) for p in planned):
            raise InputError(f"no measured rows outside the test set from {start} for {days} days "
                             f"in {workdir} to choose from (--from-existing); choose dates of the "
                             "logs")
    else:
        grid = slot_grid(site, start, days, spacing_s, max(1, round(NODE_MINUTES * 60 / spacing_s)),
                         min_elevation_deg)
    year_sun = year_sun_grid(site, start, YEAR_EVERY_DAYS, YEAR_EVERY_MINUTES, min_elevation_deg)
    designs, row_jacs, noise = _designs(planned, year_sun,
                                        None if grid is None else grid.sun[grid.nodes],
                                        from_existing, workers)
    if grid is None:
        candidates = RowCandidates(designs, row_jacs,
                                   [p.candidates["day"].to_numpy(int) for p in planned])
    else:
        candidates = GridCandidates(grid, designs, [p.targets for p in planned])
    picks, _ = greedy_schedule(designs, candidates, limits)
    exact = _exact_rows(planned, designs, picks, grid) if grid is not None else {}
    plan, covs, dropped = _plan_rows(planned, designs, picks, exact, grid)
    opts = {"start": start, "days": days, "per_day": limits.per_day, "budget": budget,
            "max_per_heliostat": max_per_heliostat, "from_existing": from_existing,
            "spacing_s": None if from_existing else spacing_s,
            "min_elevation_deg": min_elevation_deg,
            "heliostats": list(heliostats) if heliostats else None}
    write_artifact(plan, workdir, PLAN, stage="plan", options=opts, seed=seed)
    current_transaction(workdir, "plan").write_bytes("plan.csv", _csv_bytes(plan))
    return _summary(workdir, plan, planned, designs, covs, row_jacs, grid, limits,
                    seed, site, noise, dropped, picks,
                    {**opts, "spacing_source": None if from_existing else spacing_source,
                     "per_day_source": per_day_source})


def _summary(workdir, plan, planned, designs, covs, row_jacs, grid, limits, seed, site,
             noise, dropped, picks, options) -> dict:
    """The stage's result: options, the field's expected errors now, after the plan and after a
    random schedule of the same rows per heliostat, and per heliostat its numbers."""
    counts = plan["heliostat_id"].value_counts()
    index = {p.item.heliostat_id: k for k, p in enumerate(planned)}
    n = np.zeros(len(planned), int)
    for hid, c in counts.items():
        n[index[hid]] = int(c)
    now = np.array([d.variance_mrad2 for d in designs])
    after = np.array([year_variance_mrad2(c, d.information) for c, d in zip(covs, designs)])
    random = _random_baseline(planned, designs, n, grid, row_jacs, seed)
    rms = lambda v: float(np.mean(np.sqrt(np.clip(v, 0.0, None))))  # noqa: E731
    guided_gain = np.array([p.gain_mrad2 for p in picks])
    exact_gain = plan["expected_gain_mrad2"].to_numpy(float)
    heliostats = [{"heliostat_id": p.item.heliostat_id, "coarse_model": p.model,
                   "known_rows": p.n_known, "planned_rows": int(n[k]),
                   "noise_mrad": designs[k].covariance.noise_mrad,
                   "expected_error_now_mrad": math.sqrt(max(now[k], 0.0)),
                   "expected_error_after_mrad": math.sqrt(max(after[k], 0.0))}
                  for k, p in enumerate(planned)]
    return {
        "workdir": str(workdir), "plan": str(workdir / PLAN.filename),
        "csv": str(workdir / "plan.csv"), **options,
        "site": list(site), "budget_total": limits.budget, "planned_rows": len(plan),
        "planned_heliostats": int((n > 0).sum()), "heliostats_considered": len(planned),
        "without_coarse_fit": [p.item.heliostat_id for p in planned if p.model.startswith("nominal:")],
        "field_noise_mrad": noise, "dropped_out_of_reach": dropped,
        "expected_error_now_mrad": rms(now), "expected_error_after_plan_mrad": rms(after),
        "expected_error_after_random_mrad": rms(random),
        "guided_gain_max_relative_difference": (
            float(np.max(np.abs(guided_gain[:len(exact_gain)] - exact_gain))
                  / max(float(np.max(exact_gain)), 1e-300)) if len(exact_gain) and not dropped
            else None),
        "heliostats": heliostats,
    }
