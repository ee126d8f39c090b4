"""Changes of a heliostat over time in the simulator (the ground truth of issue 17's detection):
regime steps (a re-mount or re-homing moves actuator zero points or tilts the structure a little,
for good), episodes (the same kind of offset for a few days, then back) and slow drift (a zero
point that moves linearly in time from a start date on).

Every change is a list of *events*; an event offsets one or two angle parameters of the 28
(:func:`change_parameters`) by a vector whose Euclidean norm is its ``size_mrad`` [mrad of the
parameters, i.e. 1e-3 rad]. An offset of an actuator zero point (``axis_i_initial_angle_rad``)
by 1 mrad turns the mirror normal by about 1 mrad; ``effect_mrad`` (set by the simulator) is the
mean angle the event turns the heliostat's normals at its own measured motor positions, the
number a detector can see.

Draws come from their own generator (``numpy.random.default_rng([seed, 17])``), so a field
simulated without changes is exactly the field of earlier versions for the same seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from ..errors import ParameterError
from ..physics.parameters import PARAMETER_INDEX, PARAMETER_NAMES, STONE_MAPPING

__all__ = [
    "CHANGE_KINDS",
    "Changes",
    "change_offsets",
    "change_parameters",
    "draw_changes",
    "event_json",
    "score_detection",
]

#: The kinds of change events: ``step`` (lasting), ``episode`` (a few days, then back), ``drift``
#: (linear in time from its start on).
CHANGE_KINDS = ("step", "episode", "drift")

_DAY = pd.Timedelta(days=1)
_SECONDS_PER_YEAR = 365.25 * 86400.0


def change_parameters(kinematic_type: str) -> tuple[str, ...]:
    """Parameters a re-mount or re-homing plausibly moves: the two actuator zero points and
    Stone's tilts alpha, beta (axis 1) and delta (mirror) of the kinematic type."""
    stone = STONE_MAPPING[kinematic_type]
    return ("axis_1_initial_angle_rad", "axis_2_initial_angle_rad",
            stone["alpha"], stone["beta"], stone["delta"])


@dataclass(frozen=True)
class Changes:
    """Which heliostats change and how much (each heliostat draws its own events).

    Attributes
    ----------
    step_fraction, episode_fraction, drift_fraction : probability that a heliostat gets regime
        steps / episodes / a drift (independent draws; a heliostat may get several kinds).
    steps : (min, max) regime steps of a heliostat that has steps.
    step_mrad : (low, high) size of a step [mrad], uniform.
    episodes : (min, max) episodes of a heliostat that has episodes.
    episode_days : (min, max) whole days an episode lasts (it starts at midnight UTC).
    episode_mrad : (low, high) size of an episode's offset [mrad], uniform.
    drift_mrad_per_year : (low, high) rate of a drift [mrad per year], uniform.
    margin_days : events start at least this many days after the period's start and before its
        end, and at least this many days apart (so every regime has rows on both sides).
    zero_point_share : probability that an event moves actuator zero points (one or both);
        otherwise it moves one tilt.
    """

    step_fraction: float = 0.0
    episode_fraction: float = 0.0
    drift_fraction: float = 0.0
    steps: tuple[int, int] = (1, 2)
    step_mrad: tuple[float, float] = (1.0, 4.0)
    episodes: tuple[int, int] = (1, 2)
    episode_days: tuple[int, int] = (1, 4)
    episode_mrad: tuple[float, float] = (2.0, 15.0)
    drift_mrad_per_year: tuple[float, float] = (1.0, 3.0)
    margin_days: float = 20.0
    zero_point_share: float = 0.7

    def __post_init__(self):
        for name in ("step_fraction", "episode_fraction", "drift_fraction", "zero_point_share"):
            v = getattr(self, name)
            if not 0.0 <= float(v) <= 1.0:
                raise ParameterError(f"The '{name}' parameter of Changes must be in [0, 1]. "
                                     f"Got {v!r} instead.")
        for name in ("steps", "step_mrad", "episodes", "episode_days", "episode_mrad",
                     "drift_mrad_per_year"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ParameterError(f"The '{name}' parameter of Changes must be (low, high) with "
                                     f"0 <= low <= high. Got {(lo, hi)!r} instead.")

    @property
    def any(self) -> bool:
        """True if some heliostat may change."""
        return max(self.step_fraction, self.episode_fraction, self.drift_fraction) > 0.0


def _direction(rng: np.random.Generator, kinematic_type: str, share: float) -> dict[str, float]:
    """Unit vector of an event's offset over the parameters it moves."""
    names = change_parameters(kinematic_type)
    if rng.random() < share:
        moved = [names[int(rng.integers(0, 2))]] if rng.random() < 0.5 else list(names[:2])
    else:
        moved = [names[int(rng.integers(2, len(names)))]]
    v = rng.normal(size=len(moved))
    v /= np.linalg.norm(v)
    return {n: float(x) for n, x in zip(moved, v)}


def _dates(rng, count: int, t0: pd.Timestamp, t1: pd.Timestamp, margin_days: float,
           taken: list[pd.Timestamp]) -> list[pd.Timestamp]:
    """``count`` event days (midnight UTC) in the period, ``margin_days`` from its ends and from
    each other and from ``taken``; fewer if the period is too short."""
    lo, hi = t0 + margin_days * _DAY, t1 - margin_days * _DAY
    out: list[pd.Timestamp] = []
    if hi <= lo:
        return out
    span_days = (hi - lo) / _DAY
    for _ in range(50 * max(count, 1)):
        if len(out) >= count:
            break
        day = (lo + float(rng.uniform(0.0, span_days)) * _DAY).normalize()
        if all(abs((day - d) / _DAY) >= margin_days for d in taken + out):
            out.append(day)
    return sorted(out)


def draw_changes(rng: np.random.Generator, changes: Changes, kinematic_type: str,
                 t0: pd.Timestamp, t1: pd.Timestamp) -> list[dict]:
    """The change events of one heliostat (possibly none), in time order.

    Each event is a JSON-ready dict: ``kind`` (:data:`CHANGE_KINDS`), ``start`` (ISO date),
    ``end`` (ISO date of the first day back to normal for an episode; the period's end for a step
    and a drift), ``size_mrad`` (steps, episodes) or ``rate_mrad_per_year`` (drift), and
    ``parameters``: {name: offset [rad]} at full size (for a drift: per year).
    """
    events: list[dict] = []
    taken: list[pd.Timestamp] = []
    share = changes.zero_point_share
    if rng.random() < changes.step_fraction:
        n = int(rng.integers(changes.steps[0], changes.steps[1] + 1))
        for day in _dates(rng, n, t0, t1, changes.margin_days, taken):
            size = float(rng.uniform(*changes.step_mrad))
            d = _direction(rng, kinematic_type, share)
            events.append({"kind": "step", "start": day, "end": t1, "size_mrad": size,
                           "parameters": {k: v * size * 1e-3 for k, v in d.items()}})
            taken.append(day)
    if rng.random() < changes.episode_fraction:
        n = int(rng.integers(changes.episodes[0], changes.episodes[1] + 1))
        for day in _dates(rng, n, t0, t1, changes.margin_days, taken):
            days = int(rng.integers(changes.episode_days[0], changes.episode_days[1] + 1))
            size = float(rng.uniform(*changes.episode_mrad))
            d = _direction(rng, kinematic_type, share)
            events.append({"kind": "episode", "start": day, "end": day + days * _DAY,
                           "size_mrad": size,
                           "parameters": {k: v * size * 1e-3 for k, v in d.items()}})
            taken.append(day)
    if rng.random() < changes.drift_fraction:
        start = (t0 + float(rng.uniform(0.0, 0.5)) * (t1 - t0)).normalize()
        rate = float(rng.uniform(*changes.drift_mrad_per_year))
        name = change_parameters(kinematic_type)[int(rng.integers(0, 2))]
        sign = 1.0 if rng.random() < 0.5 else -1.0
        events.append({"kind": "drift", "start": start, "end": t1, "rate_mrad_per_year": rate,
                       "parameters": {name: sign * rate * 1e-3}})
    events.sort(key=lambda e: (e["start"], e["kind"]))
    return events


def _event_factor(event: dict, times: pd.DatetimeIndex) -> np.ndarray:
    """Share of the event's full offset at each time (0 before, 1 during a step/episode; years
    since the start for a drift)."""
    start, end = event["start"], event["end"]
    on = np.asarray((times >= start) & (times < end) if event["kind"] == "episode"
                    else times >= start)
    if event["kind"] == "drift":
        years = (times - event["start"]).total_seconds().to_numpy(float) / _SECONDS_PER_YEAR
        return np.where(on, years, 0.0)
    return on.astype(float)


def change_offsets(events: list[dict], times: pd.DatetimeIndex) -> torch.Tensor:
    """Offsets (N, 28) of the parameters at each time from a heliostat's events."""
    out = np.zeros((len(times), len(PARAMETER_NAMES)))
    for event in events:
        factor = _event_factor(event, times)
        for name, value in event["parameters"].items():
            out[:, PARAMETER_INDEX[name]] += factor * value
    return torch.as_tensor(out, dtype=torch.float64)


def event_json(event: dict) -> dict:
    """An event as written to ground_truth.json (dates as ISO strings)."""
    out = dict(event)
    out["start"] = str(event["start"].date())
    out["end"] = str(event["end"].date())
    return out


def score_detection(truth: dict, regimes: pd.DataFrame, times: dict, *, tolerance_days: float = 3.0,
                    min_mrad: float = 1.0, min_rows: int = 2, dynamic: frozenset = frozenset()) -> dict:
    """Recall and false alarms of a detection (regimes.parquet rows) against the ground truth.

    Parameters
    ----------
    truth : heliostat id -> its change events (ground_truth.json's ``changes`` lists).
    regimes : regimes.parquet's rows.
    times : heliostat id -> the timestamps the detection read (UTC).
    tolerance_days : a true step or episode is found when a detected break (``cause``
        ``detected`` or ``renovation``) starts within this many days of its start; also counted
        (``found_first_row``) when it is within this many days of the first row at or after the
        start, the earliest the data can show it.
    min_mrad : events whose ``effect_mrad`` is smaller are not counted.
    min_rows : events with fewer affected rows are not observable and are not counted.
    dynamic : heliostats with dynamic disturbances (seasonal tilt, drift, ...): without events
        they are not static; their breaks are counted apart (``dynamic_alarms``).

    Returns
    -------
    dict: ``events`` (counted), ``found``, ``found_first_row``, ``recall``, ``recall_first_row``,
    ``static_heliostats``, ``static_years``, ``static_false_alarms`` (detected breaks on
    heliostats without events), ``false_alarms_per_10_years``, ``unobservable`` (events left
    out for too few rows), ``missed`` (list of the missed events).
    """
    day = pd.Timedelta(days=1)
    breaks = regimes[regimes["cause"].isin(["detected", "renovation"])]
    starts = {h: pd.to_datetime(g["start"], utc=True) for h, g in breaks.groupby("heliostat_id")}
    counted = found = found_row = unobservable = 0
    missed = []
    static_years, static_alarms, static_n = 0.0, 0, 0
    dyn_years, dyn_alarms, dyn_n = 0.0, 0, 0
    for hid, events in truth.items():
        t = pd.DatetimeIndex(pd.to_datetime(pd.Series(times.get(hid, [])), utc=True)).sort_values()
        detected = starts.get(hid, pd.Series([], dtype="datetime64[ns, UTC]"))
        if not events:
            if len(t) > 1 and hid in dynamic:
                dyn_n += 1
                dyn_years += (t[-1] - t[0]) / day / 365.25
                dyn_alarms += int(len(detected))
            elif len(t) > 1:
                static_n += 1
                static_years += (t[-1] - t[0]) / day / 365.25
                static_alarms += int(len(detected))
            continue
        for e in events:
            if e["kind"] == "drift":
                continue
            start = pd.Timestamp(e["start"], tz="UTC")
            end = pd.Timestamp(e["end"], tz="UTC")
            rows_in = (t >= start) & (t < end) if e["kind"] == "episode" else t >= start
            if int(rows_in.sum()) < min_rows or (e["kind"] == "step" and int((t < start).sum()) < min_rows):
                unobservable += 1
                continue
            if e.get("effect_mrad", 0.0) < min_mrad:
                continue
            counted += 1
            first = t[t >= start][0]
            gap = np.abs((detected - start) / day).min() if len(detected) else np.inf
            gap_row = np.abs((detected - first) / day).min() if len(detected) else np.inf
            found += bool(gap <= tolerance_days)
            found_row += bool(gap_row <= tolerance_days)
            if gap_row > tolerance_days:
                missed.append({"heliostat_id": hid, **{k: e[k] for k in ("kind", "start", "end")},
                               "size_mrad": e.get("size_mrad"), "effect_mrad": e.get("effect_mrad"),
                               "rows": int(rows_in.sum()), "nearest_break_days": float(gap_row)})
    return {"events": counted, "found": found, "found_first_row": found_row,
            "recall": found / counted if counted else float("nan"),
            "recall_first_row": found_row / counted if counted else float("nan"),
            "unobservable": unobservable, "static_heliostats": static_n,
            "static_years": static_years, "static_false_alarms": static_alarms,
            "false_alarms_per_10_years": 10.0 * static_alarms / static_years if static_years else float("nan"),
            "dynamic_heliostats": dyn_n, "dynamic_years": dyn_years, "dynamic_alarms": dyn_alarms,
            "dynamic_alarms_per_10_years": 10.0 * dyn_alarms / dyn_years if dyn_years else float("nan"),
            "missed": missed}
