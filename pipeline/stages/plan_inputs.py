"""What ``plan`` reads and derives from a work directory before it designs anything: the site,
the logs' pace (spacing on a target, measurements per day), and per heliostat the rows its
covariance rests on, its targets and its coarse model (:class:`PlannedHeliostat`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import torch

from ..artifacts.manifests import load_manifest
from ..errors import InputError
from ..models.coarse import MeasurementBatch, prior_sigma
from ..models.design import DesignInput
from ..models.regime_fit import base_preset
from ..models.schedule import solar_day_start
from ..physics.parameters import HeliostatSpec, nominal_parameters, preset_mask

__all__ = [
    "PriorScale",
    "default_prior_scale",
    "PlannedHeliostat",
    "plant_site",
    "log_spacing_s",
    "log_per_day",
    "solar_days",
    "planned_heliostats",
    "DEFAULT_SPACING_S",
    "FALLBACK_PRESET",
    "YOUNG_REGIME_MIN_STEP_MRAD",
    "current_regime_rows",
]

log = logging.getLogger("heliocal.plan")

#: Spacing between measurements on one target when the logs do not tell [s]: the Jülich log's
#: median gap between consecutive measurements of two heliostats on one target is 189 s.
DEFAULT_SPACING_S = 180

#: Gaps (< 1 h) on one target the logs must show before their median is the default spacing.
MIN_SPACING_GAPS = 20

#: A median gap above this [s] is no calibration session's pace (the plant measured heliostats
#: now and then, not one after the other): then the default spacing. Logs of heliostats
#: scheduled independently (simulate's) show medians of 20-26 minutes.
MAX_SESSION_SPACING_S = 600

#: A detected break moves a heliostat into a young regime (the plan's covariance then rests on
#: the rows after it only) when its step is at least this [mrad]: the smallest step
#: ``simulate`` draws. With few rows a fit's residuals are small and regime detection finds
#: steps of 0.1-0.3 mrad on static heliostats (4 of 6 simulated ones with 10 rows each).
YOUNG_REGIME_MIN_STEP_MRAD = 1.0

#: The preset of a heliostat without a coarse fit when no heliostat of its type has one.
FALLBACK_PRESET = "static-6"

#: The prior's scale of each parameter of a heliostat: ``f(heliostats.parquet row, nominal
#: parameters (28,)) -> (28,)`` [each parameter's unit]. The coarse fit's prior
#: (:func:`heliocal.pipeline.models.coarse.prior_sigma`) by default; a field prior (per
#: kinematic type and parameter) plugs in here.
PriorScale = Callable[[pd.Series, torch.Tensor], np.ndarray]


def default_prior_scale(row: pd.Series, nominal: torch.Tensor) -> np.ndarray:
    """fit-coarse's prior scale (:data:`heliocal.pipeline.models.coarse.PRIOR_SIGMA`)."""
    return prior_sigma(nominal)


def plant_site(workdir: Path, helio: pd.DataFrame) -> tuple[float, float, float]:
    """The site (lat [deg], lon [deg], height [m]): the median of the heliostats' WGS84
    positions, else ingest's ``--location``."""
    lat = pd.to_numeric(helio["latitude_deg"], errors="coerce").dropna()
    lon = pd.to_numeric(helio["longitude_deg"], errors="coerce").dropna()
    if len(lat) and len(lon):
        alt = pd.to_numeric(helio["altitude_m"], errors="coerce").dropna()
        return float(lat.median()), float(lon.median()), float(alt.median()) if len(alt) else 0.0
    m = load_manifest(workdir, "ingest")
    location = (m.data.get("options") or {}).get("location") if m is not None else None
    if location:
        return tuple(float(x) for x in location)
    raise InputError(f"the plant's location is unknown: {workdir}/heliostats.parquet has no WGS84 "
                     "positions and ingest had no --location; ingest again with --location "
                     "LAT,LON,ALT")


def solar_days(times: pd.Series, start, longitude_deg: float) -> np.ndarray:
    """Solar day of each UTC time relative to ``start`` (0 = the start date; NaN without time)."""
    first = solar_day_start(start, longitude_deg)
    t = pd.to_datetime(times, utc=True)
    return np.floor((t - first) / pd.Timedelta(days=1)).to_numpy(float)


def log_spacing_s(meas: pd.DataFrame) -> tuple[int, str]:
    """The default spacing on one target [s] and where it comes from: the median gap between
    consecutive measurements of two different heliostats on one target, counting gaps under an
    hour (the pace of a calibration session), to the nearest whole minute (at least one); else
    (fewer than :data:`MIN_SPACING_GAPS` gaps, or a median above
    :data:`MAX_SESSION_SPACING_S`) :data:`DEFAULT_SPACING_S`."""
    m = meas.dropna(subset=["timestamp"]).sort_values(["target_name", "timestamp"])
    gap = m.groupby("target_name")["timestamp"].diff().dt.total_seconds()
    other = m["heliostat_id"].ne(m.groupby("target_name")["heliostat_id"].shift())
    gaps = gap[other & (gap < 3600)].dropna()
    if len(gaps) < MIN_SPACING_GAPS:
        return DEFAULT_SPACING_S, (f"default ({len(gaps)} gaps under an hour between two heliostats "
                                   f"on one target in the logs, fewer than {MIN_SPACING_GAPS})")
    median = float(gaps.median())
    if median > MAX_SESSION_SPACING_S:
        return DEFAULT_SPACING_S, (f"default (the logs' median gap between two heliostats on one "
                                   f"target, {median:.0f} s, is no calibration session's pace)")
    return max(60, int(round(median / 60.0)) * 60), (
        f"the logs' median gap between two heliostats on one target, {median:.0f} s "
        f"({len(gaps)} gaps under an hour), in whole minutes")


def log_per_day(meas: pd.DataFrame, longitude_deg: float, n_heliostats: int) -> tuple[int, str]:
    """The default measurements per day and where it comes from: the median count of the logs'
    measurement days (solar days); without timestamps one per heliostat."""
    t = meas["timestamp"].dropna()
    if t.empty:
        return max(1, n_heliostats), "one per heliostat (the logs have no timestamps)"
    days = solar_days(t, t.min().normalize(), longitude_deg)
    counts = pd.Series(days).value_counts()
    return max(1, int(round(float(counts.median())))), (
        f"the logs' median per measurement day ({len(counts)} days)")


@dataclass
class PlannedHeliostat:
    """One heliostat of the plan: its :class:`DesignInput`, the model its covariance rests on,
    its targets' names (the order of ``item.target_points``), how many known rows, the degrees of
    freedom ``2 N - P`` of the residuals its noise scale would rest on (None without rows for
    it), and (``--from-existing``) its candidate rows."""

    item: DesignInput
    model: str
    targets: list[str]
    n_known: int
    noise_dof: int | None
    candidates: pd.DataFrame | None = None


def _targets(meas: pd.DataFrame) -> dict:
    """Per heliostat (and ``None``: the field) its target names by use (most used first) and
    their centres (T, 3) [m ENU]; one grouping of the whole table."""
    cols = ["target_e_m", "target_n_m", "target_u_m"]
    g = meas.groupby(["heliostat_id", "target_name"], sort=True)
    table = g[cols].median().assign(n=g.size())
    field = meas.groupby("target_name")[cols].median().assign(
        n=meas.groupby("target_name").size())
    out = {}
    for key, t in [(None, field)] + list(table.groupby(level=0)):
        names = t.index.get_level_values(-1)
        order = sorted(range(len(t)), key=lambda k: (-int(t["n"].iloc[k]), names[k]))
        out[key] = ([str(names[k]) for k in order], t[cols].to_numpy(float)[order])
    return out


def current_regime_rows(rows: pd.DataFrame, regimes: pd.DataFrame | None,
                  regime_aware: bool) -> tuple[np.ndarray, np.ndarray]:
    """(rows of the heliostat's current regime, rows inside an episode) of one heliostat.

    The current regime starts at the latest break that moved the heliostat: a renovation, a
    detected break of at least :data:`YOUNG_REGIME_MIN_STEP_MRAD`, or any break when the
    selected model is regime-aware (fit-coarse found the regimes worth a model of their own).
    Episodes count by the same size rule."""
    n = len(rows)
    if regimes is None or regimes.empty or rows["timestamp"].isna().all():
        return np.ones(n, bool), np.zeros(n, bool)
    t = pd.to_datetime(rows["timestamp"], utc=True)
    segments = regimes[(regimes["kind"] == "regime") & (regimes["cause"] != "start")]
    moved = segments[regime_aware | (segments["cause"] == "renovation")
                     | (segments["step_mrad"].fillna(0.0) >= YOUNG_REGIME_MIN_STEP_MRAD)]
    current = (t >= moved["start"].max()).to_numpy() if len(moved) else np.ones(n, bool)
    episode = np.zeros(n, bool)
    episodes = regimes[regimes["kind"] == "episode"]
    for _, e in episodes[episodes["step_mrad"].fillna(0.0) >= YOUNG_REGIME_MIN_STEP_MRAD].iterrows():
        episode |= ((t >= e["start"]) & (t <= e["end"])).to_numpy()
    return current, episode


def _field_presets(helio: pd.DataFrame, selected: dict) -> dict:
    """The most common selected base preset per kinematic type (ties: the smaller name)."""
    out = {}
    kinds = helio.set_index("heliostat_id")["kinematic_type"]
    names = pd.Series({h: base_preset(s["preset"]) for h, s in selected.items()})
    for kind, group in names.groupby(kinds.reindex(names.index)):
        counts = group.value_counts()
        out[kind] = sorted(counts.index, key=lambda p: (-counts[p], p))[0]
    return out


def planned_heliostats(helio: pd.DataFrame, meas: pd.DataFrame, selected: dict,
                       regimes: pd.DataFrame | None, prior: PriorScale, *, window_start=None,
                       window_days: np.ndarray | None = None,
                       days: int = 0) -> list[PlannedHeliostat]:
    """Every heliostat's design input, in ``helio``'s order.

    ``meas`` carries each row's split label (``split``; ``excluded``: a heliostat without a fit).
    A fitted heliostat's covariance rests on its training rows outside episodes in its latest
    regime (a young regime has few) at its selected model's parameters; its noise scale on the
    rows its parameters describe. A heliostat without a fit rests on all its rows at its nominal
    geometry with the field's most common preset of its type, and takes the field's noise.
    With ``window_start`` (``--from-existing``) only rows before the window are known, and the
    rows in its ``days`` (``window_days``: each row's solar day) that are not test rows are the
    candidates.
    """
    groups = dict(tuple(meas.groupby("heliostat_id", sort=False)))
    by_regime = {} if regimes is None else dict(tuple(regimes.groupby("heliostat_id", sort=False)))
    targets = _targets(meas) if len(meas) else {None: ([], np.zeros((0, 3)))}
    presets = _field_presets(helio, selected)
    out = []
    for _, hrow in helio.iterrows():
        hid = str(hrow["heliostat_id"])
        rows = groups.get(hid, meas.iloc[:0])
        spec, nominal = HeliostatSpec.from_row(hrow), nominal_parameters(hrow)
        names, points = targets.get(hid, targets[None])
        if not names:
            continue
        fit = selected.get(hid)
        regime_aware = fit is not None and fit["preset"] != fit["base_preset"]
        latest, episode = current_regime_rows(rows, by_regime.get(hid), regime_aware)
        before = np.ones(len(rows), bool)
        candidates = None
        if window_start is not None:
            day = window_days[meas.index.get_indexer(rows.index)]
            before = rows["timestamp"].notna().to_numpy() & (day < 0)
            pick = (np.isfinite(day) & (day >= 0) & (day < days)
                    & (rows["split"] != "test").to_numpy())
            candidates = rows[pick].assign(day=day[pick].astype(int))
        if fit is not None:
            train = (rows["split"] == "train").to_numpy() & ~episode
            noise_mask = train & latest if regime_aware else train
            known_mask = train & latest & before
            params, free, model = fit["params"], fit["free"].numpy(), fit["preset"]
        else:
            preset = presets.get(spec.kinematic_type, FALLBACK_PRESET)
            known_mask = before & (rows["split"] != "test").to_numpy()
            noise_mask = np.zeros(len(rows), bool)
            params = nominal
            free = preset_mask(preset, spec.actuator_type, spec.kinematic_type).numpy()
            model = f"nominal:{preset}"
        batch = MeasurementBatch.from_frame(rows) if len(rows) else None
        known = batch.subset(known_mask) if batch is not None else _empty_batch()
        noise = (known if np.array_equal(noise_mask, known_mask) else batch.subset(noise_mask)
                 ) if noise_mask.any() else None
        item = DesignInput(hid, spec, params, free, np.asarray(prior(hrow, nominal), float),
                           known, noise, points[0], points)
        dof = None if noise is None else 2 * len(noise) - int(np.sum(free))
        out.append(PlannedHeliostat(item, model, names, len(known), dof, candidates))
    return out


def _empty_batch() -> MeasurementBatch:
    z = torch.zeros((0, 3), dtype=torch.float64)
    return MeasurementBatch(np.array([], dtype=str), torch.zeros((0, 2), dtype=torch.float64),
                            z, z, z, z)
