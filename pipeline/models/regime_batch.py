"""The regime-aware candidates of many heliostats fitted together (``fit-coarse --solver batched``).

:func:`heliocal.pipeline.models.regime_fit.fit_regime_model` solves one heliostat's candidate
with :func:`scipy.optimize.least_squares`: every iteration evaluates the exact Jacobian of every
training row at its own parameters, and with two candidates per heliostat with a break that was
most of what the regimes added to ``fit-coarse``. Here the same objective (the same residuals,
priors, loss and ``f_scale``; :mod:`~heliocal.pipeline.models.regime_fit`'s docstring) is
minimised for all candidates of a chunk of heliostats of one type at once by a *chord*
Gauss-Newton method:

* The Jacobian of the residuals with respect to the 28 parameters at the plain fit (where every
  row of a heliostat has the same parameters) is the one ``fit-coarse`` computed on the plain
  fit's training rows (for its degeneracy check; else one batched call for all heliostats),
  and the ``offsets`` candidate's design matrix is built from it: the
  shared free parameters' columns as they are, each regime's offset columns as the moved
  parameters' columns on that regime's rows, each rate column as a zero point's column times the
  row's years from its regime's reference time. A row's parameters are linear in the candidate's
  variables, so this is the exact Jacobian at the start. ``drift`` nests ``offsets`` (rates 0):
  it starts at the offsets' solution, from the Jacobian last evaluated there (8 % less time
  than both starting at the plain fit).
* Chord iterations keep the design matrix and re-evaluate only the residuals (one forward pass
  of every active candidate's rows together). The step solves the Gauss-Newton normal equations
  with scipy's weights for a robust loss (gradient ``rho'``, Hessian ``rho' + 2 z rho''``; the
  prior rows carry the loss too, as in the scipy path) and is halved while it does not lower the
  cost. They stop when the step or the cost's decrease falls below the tolerance.
* Then the Jacobian is evaluated again at the point reached (each row at its own parameters).
  A candidate has *converged* when the Gauss-Newton step of this exact Jacobian would lower the
  cost by less than ``tolerance`` times the cost; otherwise chord iterations go on from the new
  design matrix. The fixed point of chord iterations alone is next to the optimum, not at it (the
  Jacobian moves with the offsets), and on flat valleys (the Jülich log's AK32, static-6 with
  bursts of rows) that difference moved the validation error by 0.07 mrad; with the exact
  check the solutions agree with scipy's to a relative 1.4e-6 in cost and 4e-3 mrad in
  validation error (fit-coarse on sample_data, the Jülich log and 120 simulated heliostats with
  changes; tests/test_regime_fit.py and tests/test_coarse_batched.py compare the two solvers).

Most candidates need two or three Jacobian evaluations (scipy: four to six) and a few residual
evaluations, all batched over the chunk. Memory: the Jacobian of the chunk's training rows,
(rows, 3, 28) float64, about 0.7 kB per row.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..physics.jacobian import residual_and_jacobian
from ..physics.lm import NAN_RESIDUAL_MRAD, normal_residuals_mrad, stack_specs, take_spec
from ..physics.parameters import PARAMETER_INDEX, HeliostatSpec
from .coarse import MeasurementBatch
from .regime_candidates import CandidateSetup
from .regime_fit import REGIME_MODELS, RegimeFit, prior_rows, regime_layout

__all__ = ["fit_candidates_batched"]


@dataclass
class _Candidate:
    """One heliostat's candidate of one model, while it is fitted."""

    h: int                    # index of the heliostat in the batch
    model: str
    layout: object            # regime_fit.RegimeLayout
    rows: np.ndarray          # (n,) indices of its training rows in the batch's flat rows
    base: np.ndarray          # (28,) the plain fit: the start and the fixed parameters
    free_idx: np.ndarray
    moved_idx: list
    drift_idx: list
    mean: np.ndarray          # (V,) prior means
    scale: np.ndarray         # (V,) prior sigmas
    x: np.ndarray             # (V,) the variables
    design: np.ndarray | None = None   # (3 n, V) the data rows' Jacobian
    j28: np.ndarray | None = None      # (n, 3, 28) the 28-parameter Jacobian it was built from
    residual: np.ndarray | None = None  # (3 n,) at x
    cost: float = float("inf")
    step: np.ndarray | None = None
    alpha: float = 1.0
    evaluations: int = 0      # residual evaluations of the chord iterations
    jacobians: int = 0        # evaluations of the Jacobian at its point
    done: bool = False
    converged: bool = False   # the exact Gauss-Newton step gains less than the tolerance
    message: str = ""

    @property
    def n_off(self) -> int:
        return len(self.moved_idx)

    @property
    def n_free(self) -> int:
        return len(self.free_idx)

    def unpack(self, x: np.ndarray):
        """(shared parameters (28,), offsets (F, n_off), rates (F, n_rate)) of variables x."""
        n_f = len(self.layout.fitted)
        p, n_off = self.n_free, self.n_off
        shared = self.base.copy()
        shared[self.free_idx] = x[:p]
        offsets = np.vstack([np.zeros(n_off), x[p:p + (n_f - 1) * n_off].reshape(-1, n_off)])
        rates = x[p + (n_f - 1) * n_off:].reshape(n_f, len(self.drift_idx))
        return shared, offsets, rates

    def row_parameters(self, x: np.ndarray) -> np.ndarray:
        """(n, 28) parameters of the training rows at variables x (training rows lie inside
        their regime's span, so the drift is not held)."""
        shared, offsets, rates = self.unpack(x)
        k = self.layout.k
        p = np.repeat(shared[None], len(k), axis=0)
        p[:, self.moved_idx] += offsets[k]
        if self.drift_idx:
            p[:, self.drift_idx] += rates[k] * self.layout.years[:, None]
        return p

    def set_design(self, j28: np.ndarray) -> None:
        """The data rows' Jacobian (3 n, V) from the 28-parameter one of the rows (n, 3, 28)."""
        lay, n = self.layout, len(self.rows)
        n_f, p, n_off, n_rate = len(lay.fitted), self.n_free, self.n_off, len(self.drift_idx)
        d = np.zeros((n, 3, len(self.x)))
        d[:, :, :p] = j28[:, :, self.free_idx]
        # each row's offset (rate) columns are those of its regime: one indexed assignment per
        # kind, rows by columns (the indexed axes come first: (rows, columns, 3))
        later = np.flatnonzero(lay.k >= 1)
        cols = p + (lay.k[later, None] - 1) * n_off + np.arange(n_off)
        d[later[:, None], :, cols] = j28[later][:, :, self.moved_idx].transpose(0, 2, 1)
        if n_rate:
            cols = p + (n_f - 1) * n_off + lay.k[:, None] * n_rate + np.arange(n_rate)
            d[np.arange(n)[:, None], :, cols] = (j28[:, :, self.drift_idx]
                                                 * lay.years[:, None, None]).transpose(0, 2, 1)
        self.design = d.reshape(3 * n, -1)


def _rho(r: np.ndarray, loss: str, f_scale: float):
    """scipy's loss of residuals r: (rho, rho', the weight of the Gauss-Newton Hessian) per
    residual. rho is scaled by ``f_scale**2`` as in
    :func:`heliocal.pipeline.physics.lm.robust_loss`; the Hessian's weight is scipy's
    ``rho' + 2 z rho''`` (z = (r / f_scale)^2; ``scale_for_robust_loss_function``), which makes
    the step a Newton step of the loss (plain reweighting, ``rho'`` alone, converges only
    linearly where residuals are several f_scale)."""
    z = (r / f_scale) ** 2
    if loss == "linear":
        one = np.ones_like(r)
        return r**2, one, one
    if loss == "soft_l1":
        t = 1.0 + z
        return 2.0 * (np.sqrt(t) - 1.0) * f_scale**2, 1.0 / np.sqrt(t), t**-1.5
    small = z <= 1.0   # huber
    zs = np.where(small, 1.0, z)
    return (np.where(small, z, 2.0 * np.sqrt(zs) - 1.0) * f_scale**2,
            np.where(small, 1.0, 1.0 / np.sqrt(zs)), np.where(small, 1.0, _EPS))


#: Smallest Hessian weight (scipy's floor for ``rho' + 2 z rho''``).
_EPS = float(np.finfo(float).eps)


def _cost_and_step(c: _Candidate, residual: np.ndarray, x: np.ndarray, loss: str,
                   f_scale: float, step: bool = True) -> tuple[float, np.ndarray, float]:
    """Half the robust cost at x (data and prior rows), the Gauss-Newton step of it and the
    decrease of the cost the step's quadratic model predicts (``-g.step / 2``); ``step=False``:
    the cost alone (step None, decrease NaN; the normal equations are most of the time)."""
    prior = (x - c.mean) / c.scale
    rho0, w, h = _rho(np.concatenate([residual, prior]), loss, f_scale)
    if not step:
        return 0.5 * float(rho0.sum()), None, float("nan")
    h = np.maximum(h, _EPS)
    n = len(residual)
    hess = c.design.T @ (h[:n, None] * c.design)
    hess[np.diag_indices_from(hess)] += h[n:] / c.scale**2
    grad = c.design.T @ (w[:n] * residual) + w[n:] * prior / c.scale
    try:
        step = -np.linalg.solve(hess, grad)
    except np.linalg.LinAlgError:
        step = -np.linalg.lstsq(hess, grad, rcond=None)[0]
    return 0.5 * float(rho0.sum()), step, -0.5 * float(grad @ step)


class _Rows:
    """The flat training rows of a batch of heliostats of one type (one row per measurement,
    each with the spec of its heliostat), evaluated at per-row parameters."""

    def __init__(self, specs: Sequence[HeliostatSpec], data: Sequence[MeasurementBatch]):
        owner = np.concatenate([np.full(len(d), h) for h, d in enumerate(data)])
        self.spec = take_spec(stack_specs(list(specs)), torch.as_tensor(owner))
        self.steps = torch.cat([d.steps for d in data]).unsqueeze(1)
        self.sun = torch.cat([d.sun for d in data]).unsqueeze(1)
        self.focal = torch.cat([d.focal_spot for d in data]).unsqueeze(1)

    def residuals(self, idx: np.ndarray, params: np.ndarray) -> np.ndarray:
        """Residuals (len(idx), 3) [mrad] of rows idx at parameters (len(idx), 28)."""
        i = torch.as_tensor(idx)
        with torch.no_grad():
            r, _ = normal_residuals_mrad(torch.from_numpy(params), take_spec(self.spec, i),
                                         self.steps[i], self.sun[i], self.focal[i])
        return r.reshape(len(idx), 3).numpy()

    def jacobian(self, idx: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(residuals (len(idx), 3), Jacobian (len(idx), 3, 28)) of rows idx at parameters."""
        i = torch.as_tensor(idx)
        with torch.no_grad():
            r, j = residual_and_jacobian(torch.from_numpy(params), take_spec(self.spec, i),
                                         self.steps[i], self.sun[i], self.focal[i])
        r = torch.nan_to_num(r, nan=NAN_RESIDUAL_MRAD).reshape(len(idx), 3).numpy()
        j = torch.nan_to_num(j[:, 0], nan=0.0, posinf=0.0, neginf=0.0).numpy()
        return r, j


def _evaluate(rows: _Rows, cands: list[_Candidate], points: list[np.ndarray],
              jacobian: bool) -> list:
    """Residuals (and Jacobians) of every candidate's training rows at its point, in one pass."""
    idx = np.concatenate([c.rows for c in cands])
    params = np.concatenate([c.row_parameters(x) for c, x in zip(cands, points)])
    if jacobian:
        r, j = rows.jacobian(idx, params)
    else:
        r, j = rows.residuals(idx, params), None
    out, a = [], 0
    for c in cands:
        b = a + len(c.rows)
        out.append((r[a:b].reshape(-1), None if j is None else j[a:b]))
        a = b
    return out


def _iterate(rows: _Rows, cands: list[_Candidate], *, loss: str, f_scale: float,
             tolerance: float, max_iterations: int) -> None:
    """Chord iterations of every candidate (its design matrix fixed, its step at its point
    computed) until the step or the cost's decrease falls below the tolerance, no halved step
    lowers the cost, or ``max_iterations`` residual evaluations are spent."""
    for c in cands:
        c.done, c.alpha = False, 1.0
    for _ in range(max_iterations):
        active = [c for c in cands if not c.done]
        if not active:
            return
        trials = [c.x + c.alpha * c.step for c in active]
        for c, x, (r, _) in zip(active, trials, _evaluate(rows, active, trials, False)):
            c.evaluations += 1
            cost = _cost_and_step(c, r, x, loss, f_scale, step=False)[0]
            if np.isfinite(cost) and cost <= c.cost:
                small_step = (np.linalg.norm((x - c.x) / c.scale)
                              <= tolerance * (tolerance + np.linalg.norm(x / c.scale)))
                small_gain = c.cost - cost <= tolerance * c.cost
                c.x, c.residual, c.cost, c.alpha = x, r, cost, 1.0
                c.done = small_step or small_gain
                # the next step only where one follows (a candidate done here, or a rejected
                # trial, goes on from _check's step or its own halved one)
                c.step = None if c.done else _cost_and_step(c, r, x, loss, f_scale)[1]
            else:
                c.alpha *= 0.5
                c.done = c.alpha < 1.0 / 64


def _check(cands: list[_Candidate], evaluated: list, *, loss: str, f_scale: float,
           tolerance: float, reused: bool = False) -> list[_Candidate]:
    """Each candidate's design matrix from the Jacobian at its point, its step, and whether it
    has converged: the Gauss-Newton step of the exact Jacobian would lower the cost by less
    than ``tolerance`` times the cost. Returns those that have not. ``reused``: the Jacobians
    were evaluated for another candidate at the same rows' parameters (not counted)."""
    left = []
    for c, (r, j28) in zip(cands, evaluated):
        c.jacobians += not reused
        c.j28 = j28
        c.residual = r
        c.set_design(j28)
        c.cost, c.step, gain = _cost_and_step(c, r, c.x, loss, f_scale)
        c.converged = gain <= tolerance * c.cost
        if not c.converged:
            left.append(c)
    return left


def _given_start(start, use: np.ndarray):
    """(residuals (3 n,), Jacobian (n, 3, 28)) of the ``use`` rows from a heliostat's given start
    (``fit_candidates_batched``'s ``starts``), as :meth:`_Rows.jacobian` gives them; None
    without one or when a ``use`` row is not among its rows."""
    if start is None or (use & ~start[2]).any():
        return None
    r, j, mask = start
    idx = (np.cumsum(mask) - 1)[use]
    r = torch.nan_to_num(r, nan=NAN_RESIDUAL_MRAD).numpy()[idx]
    return r.reshape(-1), torch.nan_to_num(j, nan=0.0, posinf=0.0, neginf=0.0).numpy()[idx]


def fit_candidates_batched(specs: Sequence[HeliostatSpec], setups: Sequence[CandidateSetup], *,
                           loss: str = "soft_l1", f_scale_mrad: float = 1.0,
                           models: Sequence[str] = REGIME_MODELS, tolerance: float = 1e-6,
                           max_iterations: int = 10, max_refreshes: int = 10,
                           prior_weight: float = 1.0,
                           starts: Sequence | None = None) -> list[list[RegimeFit]]:
    """The regime-aware candidates of heliostats of one kinematic and actuator type (module
    docstring).

    Parameters
    ----------
    specs : the heliostats; setups : their :func:`~regime_candidates.candidate_setup` (a heliostat that
        is not ``eligible`` or has fewer than two regimes with enough training rows gets none).
    loss, f_scale_mrad, prior_weight : as :func:`~regime_fit.fit_regime_model`.
    models : the candidates, in :data:`~regime_fit.REGIME_MODELS` order.
    tolerance : a candidate has converged when the Gauss-Newton step of the exact Jacobian at
        its point would lower the cost by less than this share of it (within chord iterations:
        their step or cost decrease relative to the point or cost, scipy's xtol and ftol).
    max_iterations : residual evaluations per design matrix (halved steps included).
    max_refreshes : evaluations of the Jacobian after the start's, at most.
    starts : per heliostat, the plain fit's (residuals (n, 3), Jacobian (n, 3, 28), mask (N,)
        of its n training rows) as ``fit-coarse`` computed them (torch), or None: the
        candidates' start where they fit a subset of those rows (else it is evaluated here).

    Returns
    -------
    Per heliostat the list of its fits, as :func:`~regime_candidates.regime_candidates` takes them.
    """
    t0 = time.perf_counter()
    out: list[list[RegimeFit]] = [[] for _ in setups]
    layouts = [regime_layout(spec, s.free, s.regime, s.times, s.train, "drift") if s.eligible
               else None for spec, s in zip(specs, setups)]
    take = [h for h, lay in enumerate(layouts) if lay is not None]
    if not take:
        return out
    data = [setups[h].data.subset(layouts[h].use) for h in take]
    rows = _Rows([specs[h] for h in take], data)
    first_row = np.cumsum([0] + [len(d) for d in data])
    cands: list[_Candidate] = []
    for j, h in enumerate(take):
        s, lay = setups[h], layouts[h]
        base = s.params.to(torch.float64).numpy().copy()
        n_f, moved = len(lay.fitted), [PARAMETER_INDEX[n] for n in lay.moved]
        for model in models:
            drift = [PARAMETER_INDEX[n] for n in lay.drifting] if model == "drift" else []
            mean, scale = prior_rows(s.params.to(torch.float64), lay.free_idx, n_f, len(moved),
                                     len(drift), prior_weight)
            cands.append(_Candidate(h, model, lay, np.arange(first_row[j], first_row[j + 1]), base,
                                    lay.free_idx, moved, drift, mean, scale, mean.copy()))
    # the Jacobian at the plain fit, once per heliostat: every candidate starts there (offsets
    # and rates 0, so all rows of a heliostat have the plain fit's parameters); fit-coarse has
    # it on the plain fit's training rows, which hold the candidates' rows unless episodes moved
    start_of = {h: _given_start(starts[h], layouts[h].use) for h in take} if starts else {}
    heads = [next(c for c in cands if c.h == h) for h in take if start_of.get(h) is None]
    if heads:
        start_of.update(zip((c.h for c in heads), _evaluate(rows, heads, [c.x for c in heads],
                                                            True)))
    options = dict(loss=loss, f_scale=f_scale_mrad, tolerance=tolerance)

    def converge(group: list[_Candidate], evaluated: list, reused: bool = False) -> None:
        # chord iterations, then the Jacobian again at the point reached, until the exact
        # Gauss-Newton step gains less than the tolerance
        left = _check(group, evaluated, reused=reused, **options)
        for _ in range(max_refreshes):
            if not left:
                break
            _iterate(rows, left, max_iterations=max_iterations, **options)
            left = _check(left, _evaluate(rows, left, [c.x for c in left], True), **options)

    if "offsets" in models and "drift" in models:
        # drift nests offsets (rates 0): it starts at the offsets' solution, from the Jacobian
        # evaluated there (the rows' parameters are the same), a few chord steps from its own
        first = [c for c in cands if c.model == "offsets"]
        converge(first, [start_of[c.h] for c in first])
        of = {c.h: c for c in first}
        then = [c for c in cands if c.model == "drift"]
        for c in then:
            c.x[:len(of[c.h].x)] = of[c.h].x
        converge(then, [(of[c.h].residual, of[c.h].j28) for c in then], reused=True)
    else:
        converge(cands, [start_of[c.h] for c in cands])
    for c in cands:
        c.message = ("converged (the exact Gauss-Newton step gains less than the tolerance; "
                     f"{c.evaluations} chord steps)" if c.converged else
                     f"not converged after {c.jacobians} evaluations of the Jacobian")
    wall = (time.perf_counter() - t0) / len(cands)
    for c in cands:
        lay = c.layout
        shared, offsets, rates = c.unpack(c.x)
        js = c.design * c.scale   # columns in prior-sigma units, as the scipy path reports it
        ev = np.linalg.eigvalsh(js.T @ js)
        cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
        out[c.h].append(RegimeFit(
            c.model, setups[c.h].preset, torch.from_numpy(shared), lay.moved,
            lay.drifting if c.model == "drift" else (), lay.fitted, offsets, rates,
            lay.reference_s, lay.span_s, lay.n_train, c.jacobians, c.cost,
            f"chord Gauss-Newton: {c.message}", cond, wall))
    return out
