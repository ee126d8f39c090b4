"""A field's measurement schedule: the time slots of the coming days at the site, and the greedy
choice of which heliostat to measure in which slot (:mod:`.design` says what a row is worth).

Slots. Every target has the same slots: times ``spacing`` apart (whole seconds from the start
day's UTC midnight), on the site's solar days (a day runs from local mean solar midnight, UTC
midnight minus longitude / 15 h, so that a day's daylight is never cut), where the sun is above
the minimum elevation. A slot of a target holds one measurement, so measurements on one target
are at least ``spacing`` apart: one heliostat on the target at a time. A heliostat takes at most
one slot at a time (over all targets).

Nodes. A candidate's aim Jacobian changes slowly with the time of day, so it is evaluated exactly
only at *nodes* (every ``node_every``-th slot of each daylight run and the run's last slot) and
interpolated linearly in time between the two nodes around a slot. The greedy choice ranks a
heliostat's candidates by their gains at the nodes, then takes the free slot next to the best
node whose gain, interpolated between the nodes around it, is largest; the chosen row updates the
covariance with its interpolated Jacobian. The plan's expected gains are computed again from
exact Jacobians at the chosen times (``plan`` does; the difference is reported).

Greedy. Repeatedly the (heliostat, slot) of highest gain among those still allowed (free slot,
day under ``per_day``, heliostat under ``max_per_heliostat``) is taken and that heliostat's
covariance is updated (:func:`~heliocal.pipeline.models.uncertainty.covariance_after`), until the
budget is spent. Taking a slot only lowers other heliostats' best gains, and a row changes only
its own heliostat's covariance, so a heap of each heliostat's best gain, recomputed when popped
("lazy greedy", Minoux 1978), gives exactly the plain greedy choice. Greedy selection is the
standard heuristic of sequential optimal design (Atkinson, Donev and Tobias 2007, section 11.2)
and is within a factor (1 - 1/e) of the optimum where the criterion is submodular (Krause,
Singh and Guestrin, JMLR 9, 2008); the variance criterion is not exactly submodular, so no bound
is claimed.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import pandas as pd

from ..physics.sun import spa_sun_position, sun_vector_enu
from .design import HeliostatDesign, gains_mrad2
from .uncertainty import ParameterCovariance, covariance_after

__all__ = [
    "SlotGrid",
    "slot_grid",
    "year_sun_grid",
    "solar_day_start",
    "Limits",
    "Occupancy",
    "Pick",
    "GridCandidates",
    "RowCandidates",
    "greedy_schedule",
]


def _utc_day(date) -> pd.Timestamp:
    """Midnight UTC of ``date`` (a date, naive or aware timestamp)."""
    t = pd.Timestamp(date)
    return (t.tz_localize("UTC") if t.tzinfo is None else t.tz_convert("UTC")).normalize()


def solar_day_start(date, longitude_deg: float) -> pd.Timestamp:
    """UTC start of the site's solar day ``date`` (local mean solar midnight)."""
    return _utc_day(date) - pd.Timedelta(hours=float(longitude_deg) / 15.0)


@dataclass(frozen=True)
class SlotGrid:
    """The slots of a plan (see the module docstring); arrays over slots (S,) or nodes (N,).

    ``time`` UTC (datetime64[ns]); ``day`` the solar day (0 = the start date); ``azimuth_deg``,
    ``elevation_deg`` and ``sun`` (S, 3) the sun (NREL SPA, heliocal's convention); ``nodes`` the
    slot index of each node; ``lower``, ``upper`` the nodes around each slot and ``weight`` the
    interpolation weight of ``upper``.
    """

    time: np.ndarray
    day: np.ndarray
    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    sun: np.ndarray
    nodes: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    weight: np.ndarray
    spacing_s: int

    def __len__(self) -> int:
        return len(self.time)

    def around(self, node: int) -> np.ndarray:
        """Slots next to node ``node``: those whose lower or upper node it is (a contiguous
        range: both are non-decreasing and differ by at most one)."""
        return np.arange(np.searchsorted(self.upper, node, "left"),
                         np.searchsorted(self.lower, node, "right"))

    def interpolate(self, node_jacobian: np.ndarray, slots: np.ndarray) -> np.ndarray:
        """Aim Jacobians (K, 3, P) at ``slots`` from one target's node Jacobians (N, 3, P)."""
        w = self.weight[slots][:, None, None]
        lo = node_jacobian[self.lower[slots]].astype(float)
        hi = node_jacobian[self.upper[slots]].astype(float)
        return (1.0 - w) * lo + w * hi


def slot_grid(site: tuple[float, float, float], start, days: int, spacing_s: int,
              node_every: int, min_elevation_deg: float) -> SlotGrid:
    """The slots of ``days`` solar days from ``start`` (a date) at ``site`` (lat [deg], lon
    [deg], height [m]), ``spacing_s`` [s] apart, with the sun above ``min_elevation_deg``."""
    lat, lon, alt = site
    first = solar_day_start(start, lon)
    anchor = _utc_day(start) - pd.Timedelta(days=1)
    k0 = int(np.floor((first - anchor).total_seconds() / spacing_s))
    k1 = int(np.ceil((first + pd.Timedelta(days=days) - anchor).total_seconds() / spacing_s))
    times = anchor + pd.to_timedelta(np.arange(k0, k1 + 1) * spacing_s, unit="s")
    day = np.floor((times - first) / pd.Timedelta(days=1)).to_numpy().astype(int)
    keep = (day >= 0) & (day < days)
    times, day = times[keep], day[keep]
    az, el = spa_sun_position(times, lat, lon, alt)
    up = el > min_elevation_deg
    times, day, az, el = times[up], day[up], az[up], el[up]
    index = np.flatnonzero(up)
    # a daylight run: consecutive slots above the minimum elevation
    new_run = np.ones(len(index), bool)
    new_run[1:] = np.diff(index) != 1
    run = np.cumsum(new_run) - 1
    position = np.arange(len(index)) - np.flatnonzero(new_run)[run] if len(index) else index
    last = np.ones(len(index), bool)
    last[:-1] = run[1:] != run[:-1]
    is_node = (position % node_every == 0) | last
    nodes = np.flatnonzero(is_node)
    node_of = np.cumsum(is_node) - 1                  # the node at or before each slot
    upper = np.where(is_node, node_of, node_of + 1)
    span = (nodes[np.minimum(upper, len(nodes) - 1)] - nodes[node_of]).astype(float)
    weight = np.where(span > 0, (np.arange(len(index)) - nodes[node_of]) / np.maximum(span, 1), 0.0)
    return SlotGrid(times.to_numpy(), day, np.asarray(az), np.asarray(el),
                    sun_vector_enu(az, el), nodes, node_of, upper, weight, int(spacing_s))


def year_sun_grid(site: tuple[float, float, float], start, every_days: int, every_minutes: int,
                  min_elevation_deg: float) -> np.ndarray:
    """Unit sun vectors (G, 3) of a year from ``start`` at ``site``: every ``every_minutes`` of
    every ``every_days``-th day, above ``min_elevation_deg``; each is an equal share of the
    year's daylight time, so a mean over them is a year-round mean over operating hours."""
    lat, lon, alt = site
    first = _utc_day(start)
    days = first + pd.to_timedelta(np.arange(0, 365, every_days), unit="D")
    minutes = pd.to_timedelta(np.arange(0, 24 * 60, every_minutes), unit="min")
    times = pd.DatetimeIndex([d + m for d in days for m in minutes])
    az, el = spa_sun_position(times, lat, lon, alt)
    up = el > min_elevation_deg
    return sun_vector_enu(az[up], el[up])


@dataclass(frozen=True)
class Limits:
    """What the schedule may spend: ``budget`` measurements in all, at most ``per_day`` on a
    solar day and ``max_per_heliostat`` per heliostat (None: no limit), over ``days`` days."""

    budget: int
    days: int
    per_day: int | None = None
    max_per_heliostat: int | None = None


@dataclass
class Pick:
    """One chosen measurement: heliostat (index of its design), target (index into its targets;
    -1 for an existing row), slot (or existing row), day, the Jacobian (r, P) its update used and
    the gain [mrad^2] it was chosen with."""

    heliostat: int
    target: int
    slot: int
    day: int
    jacobian: np.ndarray
    gain_mrad2: float


@dataclass
class Occupancy:
    """What the schedule has taken so far: per target its taken slots (over ``n_slots``), per
    day and heliostat the count, per heliostat its slots (or rows)."""

    limits: Limits
    n_heliostats: int
    n_slots: int = 0
    taken: dict = field(default_factory=dict)          # target name -> (S,) bool
    day_count: np.ndarray = None
    count: np.ndarray = None
    busy: list = None
    busy_slots: dict = field(default_factory=dict)     # heliostat -> (S,) bool, once it has one

    def __post_init__(self):
        self.day_count = np.zeros(self.limits.days, int)
        self.count = np.zeros(self.n_heliostats, int)
        self.busy = [set() for _ in range(self.n_heliostats)]

    def day_open(self, days: np.ndarray) -> np.ndarray:
        d = np.asarray(days, int)
        if self.limits.per_day is None:
            return np.ones(d.shape, bool)
        return self.day_count[d] < self.limits.per_day

    def free(self, h: int, target_name: str, slots: np.ndarray, days: np.ndarray) -> np.ndarray:
        """Which of ``slots`` heliostat ``h`` may take on ``target_name``: the target's slot is
        free, ``h`` is not measured then, the day has room."""
        ok = ~self.taken_slots(target_name)[slots] & self.day_open(days)
        if h in self.busy_slots:
            ok &= ~self.busy_slots[h][slots]
        return ok

    def taken_slots(self, target_name: str) -> np.ndarray:
        if target_name not in self.taken:
            self.taken[target_name] = np.zeros(self.n_slots, bool)
        return self.taken[target_name]

    def room_for(self, h: int) -> bool:
        cap = self.limits.max_per_heliostat
        return cap is None or self.count[h] < cap

    def take(self, pick: Pick, target_name: str | None) -> None:
        if target_name is not None:
            self.taken_slots(target_name)[pick.slot] = True
            self.busy_slots.setdefault(pick.heliostat, np.zeros(self.n_slots, bool))[pick.slot] = True
        self.busy[pick.heliostat].add(pick.slot)
        self.day_count[pick.day] += 1
        self.count[pick.heliostat] += 1


def _finite_or_floor(g: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(g), g, -np.inf)


class GridCandidates:
    """Candidates on a :class:`SlotGrid`: each heliostat on each of its targets in each slot."""

    def __init__(self, grid: SlotGrid, designs: Sequence[HeliostatDesign],
                 targets: Sequence[Sequence[str]]):
        self.grid, self.designs, self.targets = grid, designs, targets
        self._gains: dict[int, tuple[int, np.ndarray]] = {}
        self._last: dict[int, tuple[int, Pick]] = {}
        self._node_day = grid.day[grid.nodes]
        self._size = np.array([len(grid.around(n)) for n in range(len(grid.nodes))])
        self._free: dict[str, np.ndarray] = {}             # target -> free slots next to a node

    def _free_next_to(self, target_name: str) -> np.ndarray:
        if target_name not in self._free:
            self._free[target_name] = self._size.copy()
        return self._free[target_name]

    def took(self, pick: Pick) -> None:
        """Count the slot ``pick`` took out of its target's free slots next to its nodes."""
        counts = self._free_next_to(self.target_name(pick))
        for n in {int(self.grid.lower[pick.slot]), int(self.grid.upper[pick.slot])}:
            counts[n] -= 1

    def _node_gains(self, h: int, cov: ParameterCovariance, version: int) -> np.ndarray:
        cached = self._gains.get(h)
        if cached is None or cached[0] != version:
            d = self.designs[h]
            j = d.node_jacobian
            g = gains_mrad2(cov, d.information, j.reshape((-1,) + j.shape[2:]))
            cached = (version, _finite_or_floor(g).reshape(j.shape[:2]))
            self._gains[h] = cached
        return cached[1]

    def best(self, h: int, cov: ParameterCovariance, version: int, occ: Occupancy) -> Pick | None:
        """Heliostat ``h``'s best allowed slot, or None (its last answer while that slot is
        still allowed and its covariance unchanged: taking slots only removes candidates)."""
        last = self._last.get(h)
        if last is not None and last[0] == version and occ.free(
                h, self.targets[h][last[1].target], np.array([last[1].slot]),
                np.array([last[1].day]))[0]:
            return last[1]
        pick = self._best(h, cov, version, occ)
        if pick is not None:
            self._last[h] = (version, pick)
        return pick

    def _best(self, h: int, cov: ParameterCovariance, version: int, occ: Occupancy) -> Pick | None:
        """The best node with a free slot next to it on a day with room, then the best of those
        slots by the gains interpolated between the nodes around it (a node whose free slots are
        all taken by ``h`` itself is skipped for ``h``); the pick's Jacobian is interpolated
        the same way."""
        gains = self._node_gains(h, cov, version)
        d, names = self.designs[h], self.targets[h]
        open_ = (np.stack([self._free_next_to(name) > 0 for name in names])
                 & occ.day_open(self._node_day)[None])
        g = np.where(open_, gains, -np.inf)
        while True:
            flat = int(np.argmax(g))
            t, n = divmod(flat, g.shape[1])
            if not np.isfinite(g[t, n]):
                return None
            slots = self.grid.around(n)
            slots = slots[occ.free(h, names[t], slots, self.grid.day[slots])]
            if len(slots):
                w = self.grid.weight[slots]
                gk = (1.0 - w) * gains[t, self.grid.lower[slots]] + w * gains[t, self.grid.upper[slots]]
                k = int(np.argmax(gk))
                if np.isfinite(gk[k]):
                    s = slots[k:k + 1]
                    return Pick(h, t, int(s[0]), int(self.grid.day[s[0]]),
                                self.grid.interpolate(d.node_jacobian[t], s)[0], float(gk[k]))
            gains[t, n] = g[t, n] = -np.inf          # nothing left next to this node for h

    def target_name(self, pick: Pick) -> str:
        return self.targets[pick.heliostat][pick.target]


class RowCandidates:
    """Candidates that are rows already measured (``plan --from-existing``): per heliostat the
    rows' data Jacobians (R, 3, P) and solar days (R,)."""

    def __init__(self, designs: Sequence[HeliostatDesign], jacobians: Sequence[np.ndarray],
                 days: Sequence[np.ndarray]):
        self.designs, self.jacobians, self.days = designs, jacobians, days
        self._gains: dict[int, tuple[int, np.ndarray]] = {}

    def best(self, h: int, cov: ParameterCovariance, version: int, occ: Occupancy) -> Pick | None:
        cached = self._gains.get(h)
        if cached is None or cached[0] != version:
            cached = (version, _finite_or_floor(
                gains_mrad2(cov, self.designs[h].information, self.jacobians[h])))
            self._gains[h] = cached
        g = cached[1].copy()
        g[list(occ.busy[h])] = -np.inf
        g[~occ.day_open(self.days[h])] = -np.inf
        if not len(g) or not np.isfinite(g.max()):
            return None
        k = int(np.argmax(g))
        return Pick(h, -1, k, int(self.days[h][k]), self.jacobians[h][k], float(g[k]))

    def target_name(self, pick: Pick) -> None:
        return None

    def took(self, pick: Pick) -> None:
        """Nothing to count: a row is taken once (Occupancy.busy)."""


def greedy_schedule(designs: Sequence[HeliostatDesign], candidates, limits: Limits
                    ) -> tuple[list[Pick], list[ParameterCovariance]]:
    """The greedy schedule (module docstring): the picks in the order taken (highest gain first)
    and every heliostat's covariance after them."""
    covs = [d.covariance for d in designs]
    occ = Occupancy(limits, len(designs), len(getattr(candidates, "grid", ())))
    version = [0] * len(designs)
    heap: list[tuple[float, int]] = []
    for h in range(len(designs)):
        first = candidates.best(h, covs[h], 0, occ) if occ.room_for(h) else None
        if first is not None:
            heap.append((-first.gain_mrad2, h))
    heapq.heapify(heap)
    picks: list[Pick] = []
    while heap and len(picks) < limits.budget:
        _, h = heapq.heappop(heap)
        pick = candidates.best(h, covs[h], version[h], occ)
        if pick is None:
            continue
        if heap and pick.gain_mrad2 < -heap[0][0]:    # another heliostat may be better now
            heapq.heappush(heap, (-pick.gain_mrad2, h))
            continue
        occ.take(pick, candidates.target_name(pick))
        candidates.took(pick)
        picks.append(pick)
        covs[h] = covariance_after(covs[h], pick.jacobian[None])
        version[h] += 1
        if occ.room_for(h):
            nxt = candidates.best(h, covs[h], version[h], occ)
            if nxt is not None:
                heapq.heappush(heap, (-nxt.gain_mrad2, h))
    return picks, covs
