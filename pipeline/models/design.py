"""What one more calibration row would teach a heliostat: optimal design on the coarse fit's
posterior covariance (:mod:`heliocal.pipeline.models.uncertainty`).

The criterion is the heliostat's expected year-round aim error. An aim at sun position ``g``
has the expected squared normal error ``trace(J_g C J_g^T)`` [mrad^2] (``J_g`` the aim
Jacobian (3, P), ``C`` the free parameters' posterior covariance); its mean over a grid of the
sun positions of a year at the site is

    V(C) = mean_g trace(J_g C J_g^T) = trace(C M),      M = mean_g J_g^T J_g   (P, P)

so ``M`` (the year's *information matrix*) is computed once per heliostat and ``V`` costs a
trace. Minimising ``V`` is I-optimal (integrated-variance) design, equivalently A-optimal design
with the weight matrix ``M`` (Atkinson, Donev and Tobias, *Optimum Experimental Designs, with
SAS*, Oxford 2007, sections 10.6 and 10.8). A measured row with Jacobian ``A`` (r, P) and noise
scale ``s`` per component changes ``C`` to ``C' = C - C A^T (s^2 I + A C A^T)^-1 A C``
(:func:`~heliocal.pipeline.models.uncertainty.covariance_after`), so its *gain* is

    V(C) - V(C') = trace((s^2 I + A C A^T)^-1 A C M C A^T)      [mrad^2]

evaluated here for many candidates at once (a 3 x 3 solve each). Gains shrink as rows are added
(diminishing returns), and they are largest where the year's aims are sensitive to parameters
the rows so far leave uncertain: sun positions far from the measured ones in the directions that
matter, i.e. the coverage gaps of the sun-position distribution, without a separate term.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..physics.kinematics import inverse_kinematics
from ..physics.lm import stack_specs
from ..physics.parameters import HeliostatSpec
from .coarse import MeasurementBatch
from .uncertainty import ParameterCovariance, aim_jacobian, coarse_covariance

__all__ = [
    "year_information",
    "year_variance_mrad2",
    "gains_mrad2",
    "DesignInput",
    "HeliostatDesign",
    "heliostat_designs",
    "aim_rows",
]


def year_information(jacobian: np.ndarray) -> np.ndarray:
    """The year's information matrix ``M = mean_g J_g^T J_g`` (P, P) [mrad^2 per parameter unit
    squared] of aim Jacobians ``jacobian`` (G, 3, P) over a grid of a year's sun positions; rows
    that are not finite (aims the heliostat cannot reach) are left out. All-NaN gives NaN."""
    j = np.asarray(jacobian, float)
    ok = np.isfinite(j).all(axis=(1, 2))
    if not ok.any():
        return np.full((j.shape[-1], j.shape[-1]), np.nan)
    jf = j[ok].reshape(-1, j.shape[-1])
    return jf.T @ jf / float(ok.sum())


def year_variance_mrad2(cov: ParameterCovariance, information: np.ndarray) -> float:
    """Expected year-round mean squared aim error ``trace(C M)`` [mrad^2]: the mean over the
    year's grid of :func:`~heliocal.pipeline.models.uncertainty.aim_variance_mrad2`."""
    return float(np.einsum("pq,qp->", cov.covariance, information))


def gains_mrad2(cov: ParameterCovariance, information: np.ndarray,
                jacobian: np.ndarray) -> np.ndarray:
    """(K,) the reduction of :func:`year_variance_mrad2` [mrad^2] by measuring each candidate
    row alone, with Jacobians ``jacobian`` (K, r, P) and the fit's noise scale (module
    docstring); NaN where a candidate's Jacobian is not finite."""
    j = np.asarray(jacobian, float)
    if j.ndim == 2:
        j = j[None]
    ok = np.isfinite(j).all(axis=(1, 2))
    out = np.full(len(j), np.nan)
    if not ok.any():
        return out
    jo = j[ok]
    jc = jo @ cov.covariance                                       # (K, r, P)
    a = jc @ jo.transpose(0, 2, 1)                                 # J C J^T
    b = jc @ information @ jc.transpose(0, 2, 1)                   # J C M C J^T
    s2 = max(cov.noise_mrad, 1e-6) ** 2                            # covariance_after's floor
    system = a + s2 * np.eye(j.shape[1])
    out[ok] = np.trace(np.linalg.solve(system, b), axis1=1, axis2=2)
    return out


@dataclass
class DesignInput:
    """What the design of one heliostat needs (all positions ENU [m]).

    Attributes
    ----------
    heliostat_id, spec : the heliostat.
    params : (28,) the coarse model's parameters (its latest regime's for a regime-aware
        model; the nominal geometry for a heliostat without a fit).
    free : (28,) bool, the free parameters of that model's preset.
    prior_sigma : (28,) the prior's scale of every parameter [its unit].
    known : the rows the covariance rests on (the latest regime's training rows).
    noise_rows : the rows whose residuals give the noise scale s (the fit's training rows).
    noise_mrad : s itself [mrad per residual component] instead (a heliostat without a fit of
        its own takes the field's); None: from ``noise_rows``.
    year_aim : (3,) aim point of the year's aims (the heliostat's most used target).
    target_points : (T, 3) the targets candidate rows may use.
    """

    heliostat_id: str
    spec: HeliostatSpec
    params: torch.Tensor
    free: np.ndarray
    prior_sigma: np.ndarray
    known: MeasurementBatch
    noise_rows: MeasurementBatch | None
    year_aim: np.ndarray
    target_points: np.ndarray
    noise_mrad: float | None = None


@dataclass
class HeliostatDesign:
    """One heliostat's design state: its covariance now, the year's information matrix, and the
    aim Jacobians of candidate rows at the schedule's nodes.

    ``node_jacobian`` (T, N, 3, P) float32 [mrad per parameter unit]: per target of
    :attr:`DesignInput.target_points` and node time, NaN where the target cannot be reached.
    ``node_steps`` (T, N, 2): the motor steps of those aims.
    """

    heliostat_id: str
    covariance: ParameterCovariance
    information: np.ndarray
    node_jacobian: np.ndarray | None = None
    node_steps: np.ndarray | None = None

    @property
    def variance_mrad2(self) -> float:
        """:func:`year_variance_mrad2` of the covariance now."""
        return year_variance_mrad2(self.covariance, self.information)


def _covariance(item: DesignInput) -> ParameterCovariance:
    """The covariance on the known rows, with the noise scale of the fit's rows."""
    sigma = np.asarray(item.prior_sigma, float)[np.asarray(item.free, bool)]
    if item.noise_mrad is not None:
        return coarse_covariance(item.spec, item.params, item.free, item.known, sigma,
                                 noise_mrad=item.noise_mrad)
    fitted = coarse_covariance(item.spec, item.params, item.free, item.noise_rows, sigma)
    if item.noise_rows is item.known:
        return fitted
    return coarse_covariance(item.spec, item.params, item.free, item.known, sigma,
                             noise_mrad=fitted.noise_mrad)


def aim_rows(items: Sequence[DesignInput], sun: np.ndarray, aims: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Motor steps (H, M, 2) and aim Jacobians (H, M, 3, P) of aims of heliostats ``items`` (one
    kinematic and actuator type, one free set) for unit sun vectors ``sun`` (M, 3) or (H, M, 3)
    and aim points ``aims`` (H, M, 3) [m ENU], through the inverse kinematics of each one's
    ``params``; NaN rows where an aim is out of reach. One batched evaluation."""
    free_idx = np.flatnonzero(np.asarray(items[0].free, bool))
    spec = stack_specs([i.spec for i in items])
    params = torch.stack([i.params.to(torch.float64) for i in items])
    s = torch.as_tensor(np.array(np.broadcast_to(sun, aims.shape), dtype=np.float64))
    a = torch.as_tensor(np.array(aims, dtype=np.float64))
    steps = inverse_kinematics(params, spec, s, a)
    return steps.numpy(), aim_jacobian(spec, params, free_idx, steps, s, a)


def heliostat_designs(items: Sequence[DesignInput], year_sun: np.ndarray,
                      node_sun: np.ndarray | None) -> list[HeliostatDesign]:
    """The designs of heliostats of one kinematic and actuator type and one free set: each one's
    covariance, the year's information matrix at ``year_sun`` (G, 3) [unit sun vectors] aimed at
    its ``year_aim``, and (unless ``node_sun`` is None) the aim Jacobians and steps of candidate
    rows on each of its targets at the node sun vectors ``node_sun`` (N, 3). Batched: one inverse
    kinematics and one Jacobian evaluation for the chunk per target slot."""
    year_aims = np.stack([np.broadcast_to(i.year_aim, year_sun.shape) for i in items])
    _, year_j = aim_rows(items, year_sun, year_aims)
    designs = [HeliostatDesign(i.heliostat_id, _covariance(i), year_information(year_j[k]))
               for k, i in enumerate(items)]
    if node_sun is None:
        return designs
    n_targets = max(len(i.target_points) for i in items)
    n_free = year_j.shape[-1]
    jac = np.full((len(items), n_targets, len(node_sun), 3, n_free), np.nan, np.float32)
    steps = np.full((len(items), n_targets, len(node_sun), 2), np.nan)
    for t in range(n_targets):
        # heliostats with fewer targets repeat their first one here and are cut off below
        aims = np.stack([np.broadcast_to(i.target_points[t if t < len(i.target_points) else 0],
                                         node_sun.shape) for i in items])
        steps[:, t], jac[:, t] = aim_rows(items, node_sun, aims)
    for k, (i, d) in enumerate(zip(items, designs)):
        d.node_jacobian = jac[k, :len(i.target_points)]
        d.node_steps = steps[k, :len(i.target_points)]
    return designs
