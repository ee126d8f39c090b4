"""How far could any covariance-based plan get on ``benchmarks/plan_sim.py``'s fields? An oracle.

``plan_sim.py`` measures one noise draw per arm. This script computes the *expected* year-round
error of a set of rows instead, from the simulator's ground truth: a coarse fit is linear in its
noise near the truth (checked: the linearised estimator with the actual noise draws reproduces
plan_sim's realised errors to 1 %), so with ``J`` the rows' Jacobian at the true geometry,
``Sigma`` each row's noise covariance (the simulator's spot noise in the target plane carried
to the mirror normal), ``L`` fit-coarse's prior rows (``1 / sigma^2``, weighed against 1 mrad)
and ``d`` the true deviation from the nominal geometry, the fit's error is Gaussian with

    mean  -(J^T J + L)^-1 L d,      covariance  (J^T J + L)^-1 J^T Sigma J (J^T J + L)^-1

and the expected year-round error is the mean over a year's sun positions (every 6th day, every
20 minutes) of the expected norm of ``J_g e`` (300 seeded draws of ``e``). Arms, per heliostat
(same field as plan_sim: 10 rows over 2023, 10 more in the plan's days):

* ``plan``: ``heliocal plan --budget 10*H --max-per-heliostat 10``'s rows;
* ``oracle``: 10 rows chosen greedily (candidates every 20 minutes of the plan's days, on the
  heliostat's logged targets, or all targets with ``--all-targets``) for the lowest expected
  mean squared year error under the exact model above (truth, exact noise, the fit's prior and
  its bias): no plan built from data can know more;
* ``oracle-plan-model``: the same greedy under the plan's model (the 10-row fit's Jacobians, an
  isotropic noise of 0.19 mrad, the prior scale against that noise);
* ``random``: 10 random daylight minutes of the plan's days on logged targets, 10 draws.

Printed: each arm's field mean and its ratio to ``random``. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/plan_bound.py \\
        [--heliostats 30] [--seed 0] [--preset static-6] [--all-targets] [--out runs/plan-bound]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import plan_sim  # noqa: E402  (the same field, fits and daylight as the benchmark)

ROOT = Path(__file__).resolve().parents[1]
NOISE_MRAD = 0.4          # the benchmark's beam noise per target-plane axis
PLAN_NOISE_MRAD = 0.19    # the normal's noise per component that noise gives (RMS over rows)


def row_terms(field_, h, free_idx, sun, targets, params, spot=None):
    """(J (N, 3, P) at ``params``, noise covariance (N, 3, 3) [mrad^2], finite (N,)) of rows of
    heliostat ``h`` at unit sun vectors ``sun`` aimed at ``targets``' centres (or ``spot``)."""
    from heliocal.pipeline.models.simulator import target_plane_axes
    from heliocal.pipeline.physics.jacobian import forward_state, residual_and_jacobian
    from heliocal.pipeline.physics.kinematics import inverse_kinematics
    from heliocal.pipeline.physics.metrics import measured_normal

    sun = torch.as_tensor(np.asarray(sun, float))
    centre = torch.as_tensor(np.stack([field_.targets[t]["center_enu"] for t in targets]))
    spot = centre if spot is None else spot
    with torch.no_grad():
        steps = inverse_kinematics(params, h.spec, sun, centre)
        _, j = residual_and_jacobian(params, h.spec, steps, sun, spot)
        _, _, pos = forward_state(params, h.spec, steps)
    dn = torch.autograd.functional.jacobian(
        lambda s: measured_normal(sun, pos, s).sum(0), spot).numpy().transpose(1, 0, 2) * 1000.0
    horizontal, vertical = target_plane_axes(np.stack([field_.targets[t]["normal_enu"]
                                                       for t in targets]))
    sigma = np.linalg.norm((spot - pos).numpy(), axis=1) * NOISE_MRAD / 1000.0
    jh, jv = np.einsum("nij,nj->ni", dn, horizontal), np.einsum("nij,nj->ni", dn, vertical)
    cov = (sigma ** 2)[:, None, None] * (jh[:, :, None] * jh[:, None, :]
                                         + jv[:, :, None] * jv[:, None, :])
    j = j.numpy()[..., free_idx]
    return j, cov, np.isfinite(j).all(axis=(1, 2)) & np.isfinite(cov).all(axis=(1, 2))


def year_jacobian(field_, h, free_idx, sun, params, target="tower_target_lower"):
    """Aim Jacobians (G, 3, P) of the year's aims at ``target`` (the ones within reach)."""
    from heliocal.pipeline.physics.jacobian import residual_and_jacobian
    from heliocal.pipeline.physics.kinematics import inverse_kinematics

    s = torch.as_tensor(sun)
    aim = torch.as_tensor(np.broadcast_to(field_.targets[target]["center_enu"], sun.shape).copy())
    with torch.no_grad():
        _, j = residual_and_jacobian(params, h.spec, inverse_kinematics(params, h.spec, s, aim),
                                     s, aim)
    j = j.numpy()[..., free_idx]
    return j[np.isfinite(j).all(axis=(1, 2))]


def fit_error(info, noise, prior, deviation):
    """(mean (..., P), covariance (..., P, P)) of the fit's parameter error (module docstring)."""
    inverse = np.linalg.inv(info + np.diag(prior))
    return -inverse @ (prior * deviation), inverse @ noise @ inverse


def expected_error(info, noise, prior, deviation, year, draws):
    """Expected mean aim error [mrad] over the year's aims ``year`` (G, 3, P)."""
    mean, cov = fit_error(info, noise, prior, deviation)
    w, v = np.linalg.eigh((cov + cov.T) / 2.0)
    e = mean + draws @ (v * np.sqrt(np.clip(w, 0.0, None))).T
    return float(np.linalg.norm(np.einsum("gip,mp->mgi", year, e), axis=-1).mean())


def greedy(info, noise, cand_j, cand_noise, ok, prior, deviation, year, n=10):
    """Indices of ``n`` candidates chosen one at a time for the lowest expected mean squared
    year error ``trace(M E[e e^T])`` (with ``deviation`` None: the posterior ``trace(M C)``)."""
    jj = np.einsum("kip,kiq->kpq", cand_j, cand_j)
    jn = (np.zeros_like(jj) if cand_noise is None
          else np.einsum("kip,kij,kjq->kpq", cand_j, cand_noise, cand_j))
    jj[~ok], jn[~ok] = 0.0, 0.0
    noise = np.zeros_like(info) if noise is None else noise
    m = np.einsum("gip,giq->pq", year, year) / len(year)
    picks = []
    for _ in range(n):
        if deviation is None:
            f = np.einsum("kpq,qp->k", np.linalg.inv(info + jj + np.diag(prior)), m)
        else:
            mean, cov = fit_error(info + jj, noise + jn, prior, deviation)
            f = np.einsum("kpq,qp->k", cov + mean[:, :, None] * mean[:, None, :], m)
        f[~ok] = np.inf
        k = int(np.argmin(f))
        picks.append(k)
        info, noise = info + jj[k], noise + jn[k]
    return picks


def main(argv=None) -> int:
    from heliocal.pipeline.models.coarse import MeasurementBatch, prior_sigma
    from heliocal.pipeline.models.schedule import year_sun_grid
    from heliocal.pipeline.models.simulator import simulate_field
    from heliocal.pipeline.physics.parameters import preset_mask
    from heliocal.pipeline.physics.sun import spa_sun_position, sun_vector_enu
    from heliocal.pipeline.stages.plan import run_plan

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0, help="the field's seed")
    ap.add_argument("--preset", default="static-6", help="fit preset and deviations")
    ap.add_argument("--start", default="2024-03-01")
    ap.add_argument("--days", type=int, default=7)
    ap.add_argument("--all-targets", action="store_true",
                    help="oracle candidates on every target, not only the logged ones")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "plan-bound")
    a = ap.parse_args(argv)
    field_ = simulate_field(a.heliostats, seed=a.seed, measurements=(10, 10),
                            dynamic_fraction=0.0, noise_mrad=NOISE_MRAD, deviations=a.preset,
                            start="2023-01-01", end="2024-01-01")
    fitted = plan_sim._fit(field_, a.out / "base", a.preset)
    run_plan(a.out / "base" / "work", start=a.start, days=a.days, budget=10 * a.heliostats,
             max_per_heliostat=10, workers=1)
    plan = pd.read_parquet(a.out / "base" / "work" / "plan.parquet")
    year = year_sun_grid(field_.reference, a.start, 15, 30, 10.0)      # the plan's year grid
    dense = year_sun_grid(field_.reference, a.start, 6, 20, 10.0)
    daylight = plan_sim._daylight_minutes(field_.reference, a.start, a.days, 10.0)
    every20 = pd.DatetimeIndex(np.concatenate([daylight[d][::20] for d in range(a.days)]))
    minutes = pd.DatetimeIndex(np.concatenate([daylight[d] for d in range(a.days)]))
    cand_sun = sun_vector_enu(*spa_sun_position(every20, *field_.reference))
    names = list(field_.targets)
    rng = np.random.default_rng(0)
    rows = []
    for hid, h in field_.heliostats.items():
        free = np.flatnonzero(preset_mask(a.preset, h.spec.actuator_type,
                                          h.spec.kinematic_type).numpy())
        m = field_.measurements[field_.measurements.heliostat_id == hid]
        b = MeasurementBatch.from_frame(m)
        sigma = prior_sigma(h.nominal)[free]
        prior, deviation = 1.0 / sigma ** 2, (h.true - h.nominal).numpy()[free]
        draws = np.random.default_rng(7).standard_normal((300, len(free)))
        yd = year_jacobian(field_, h, free, dense, h.true)

        def info_of(sun, targets, params=h.true, spot=None):
            j, n, ok = row_terms(field_, h, free, sun, targets, params, spot)
            return (np.einsum("kip,kiq->pq", j[ok], j[ok]),
                    np.einsum("kip,kij,kjq->pq", j[ok], n[ok], j[ok]))

        i0, n0 = info_of(b.sun.numpy(), list(m.target_name), spot=b.focal_spot)
        expect = lambda i, n: expected_error(i0 + i, n0 + n, prior, deviation, yd, draws)  # noqa
        p = plan[plan.heliostat_id == hid]
        row = {"heliostat_id": hid, "10 rows": expect(0.0, 0.0),
               "plan": expect(*info_of(sun_vector_enu(*spa_sun_position(
                   pd.DatetimeIndex(p.time_utc), *field_.reference)), list(p.target)))}
        allowed = [t for t in names if a.all_targets or t in set(m.target_name)]
        cj, cn, ok = (np.concatenate(x) for x in zip(*[
            row_terms(field_, h, free, cand_sun, [t] * len(cand_sun), h.true) for t in allowed]))
        picks = greedy(i0, n0, cj, cn, ok, prior, deviation, year_jacobian(field_, h, free, year,
                                                                           h.true))
        sel = lambda k: (np.einsum("kip,kiq->pq", cj[k], cj[k]),  # noqa: E731
                         np.einsum("kip,kij,kjq->pq", cj[k], cn[k], cj[k]))
        row["oracle"] = expect(*sel(picks))
        fit = fitted[hid]["params"].to(torch.float64)
        fj = np.concatenate([row_terms(field_, h, free, cand_sun, [t] * len(cand_sun), fit)[0]
                             for t in allowed])
        fok = ok & np.isfinite(fj).all(axis=(1, 2))
        fi0, _ = info_of(b.sun.numpy(), list(m.target_name), fit, b.focal_spot)
        most = m["target_name"].value_counts().index[0]
        picks = greedy(fi0, None, np.where(fok[:, None, None], fj, 0.0), None, fok,
                       PLAN_NOISE_MRAD ** 2 / sigma ** 2, None,
                       year_jacobian(field_, h, free, year, fit, most))
        row["oracle-plan-model"] = expect(*sel(picks))
        random = []
        for _ in range(10):
            t = minutes[rng.integers(len(minutes), size=10)]
            logged = list(m.target_name)
            targets = [logged[i] for i in rng.integers(len(logged), size=10)]
            random.append(expect(*info_of(sun_vector_enu(*spa_sun_position(t, *field_.reference)),
                                          targets)))
        row["random"] = float(np.mean(random))
        rows.append(row)
    df = pd.DataFrame(rows).set_index("heliostat_id")
    means = df.mean()
    print(f"field seed {a.seed}: {a.heliostats} static heliostats, fit-coarse --preset {a.preset}; "
          f"oracle candidates on {'all' if a.all_targets else 'logged'} targets")
    print(f"{'arm':18s} {'expected mrad':>13s} {'x random':>9s}")
    for arm, v in means.items():
        print(f"{arm:18s} {v:13.4f} {v / means['random']:9.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
