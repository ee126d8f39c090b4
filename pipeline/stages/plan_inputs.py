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
    "regime_breaks",
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
    """Per heliostat (and ``None``: the field) its target names by use (most used first, then by
    name) and their centres (T, 3) [m ENU]; one grouping of the whole table."""
    cols = ["target_e_m", "target_n_m", "target_u_m"]
    out = {}
    for keys in (["target_name"], ["heliostat_id", "target_name"]):
        g = meas.groupby(keys, sort=False)
        t = g[cols].median().assign(n=g.size()).reset_index()
        if len(keys) == 1:
            t["heliostat_id"] = None
        t = t.sort_values(["heliostat_id", "n", "target_name"], ascending=[True, False, True],
                          na_position="first", kind="mergesort")
        hids, names, points = t["heliostat_id"].to_numpy(), t["target_name"].to_numpy(), \
            t[cols].to_numpy(float)
        cut = np.flatnonzero(np.r_[True, hids[1:] != hids[:-1], True])
        for a, b in zip(cut[:-1], cut[1:]):
            out[hids[a]] = ([str(x) for x in names[a:b]], points[a:b])
    return out


def regime_breaks(regimes: pd.DataFrame | None, regime_aware: set) -> tuple[dict, dict]:
    """(per heliostat the UTC start of its current regime, per heliostat the (start, end) spans
    of its episodes that count) from regimes.parquet's rows.

    The current regime starts at the latest break that moved the heliostat: a renovation, a
    detected break of at least :data:`YOUNG_REGIME_MIN_STEP_MRAD`, or any break of a heliostat in
    ``regime_aware`` (its selected model is regime-aware: fit-coarse found the regimes worth a
    model of their own). Episodes count by the same size rule."""
    if regimes is None or regimes.empty:
        return {}, {}
    step = regimes["step_mrad"].fillna(0.0)
    breaks = (regimes["kind"] == "regime") & (regimes["cause"] != "start")
    moved = breaks & ((regimes["cause"] == "renovation") | (step >= YOUNG_REGIME_MIN_STEP_MRAD)
                      | regimes["heliostat_id"].isin(regime_aware))
    starts = regimes[moved].groupby("heliostat_id")["start"].max().to_dict()
    episodes = regimes[(regimes["kind"] == "episode") & (step >= YOUNG_REGIME_MIN_STEP_MRAD)]
    spans = {h: list(zip(g["start"], g["end"])) for h, g in episodes.groupby("heliostat_id")}
    return starts, spans


def _utc_ns(times) -> np.ndarray:
    """UTC times as naive datetime64[ns] (NaT stays NaT: every comparison with it is False)."""
    t = pd.to_datetime(pd.Series(times), utc=True)
    return t.dt.tz_localize(None).to_numpy("datetime64[ns]")


def _utc_ns1(time) -> np.datetime64:
    t = pd.Timestamp(time)
    return np.datetime64((t.tz_convert("UTC").tz_localize(None) if t.tzinfo else t).value, "ns")


def current_regime_rows(times, start, spans) -> tuple[np.ndarray, np.ndarray]:
    """(rows of the current regime, rows inside an episode that counts) for a heliostat's row
    times (UTC; or already naive UTC datetime64[ns]), the start of its current regime (None: it
    never moved) and its episodes' spans (:func:`regime_breaks`). A row without time is in no
    regime but the first."""
    t = times if getattr(times, "dtype", None) == np.dtype("datetime64[ns]") else _utc_ns(times)
    current = np.ones(len(t), bool) if start is None else t >= _utc_ns1(start)
    episode = np.zeros(len(t), bool)
    for a, b in spans:
        episode |= (t >= _utc_ns1(a)) & (t <= _utc_ns1(b))
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


def _rows_of(meas: pd.DataFrame) -> dict:
    """Per heliostat the (first, end) positions of its rows in ``meas`` (sorted by heliostat)."""
    hids = meas["heliostat_id"].to_numpy()
    if len(hids) and (hids[1:] < hids[:-1]).any():
        raise ValueError("planned_heliostats needs the measurements sorted by heliostat_id")
    cut = np.flatnonzero(np.r_[True, hids[1:] != hids[:-1], True]) if len(hids) else np.array([0])
    return {hids[a]: (a, b) for a, b in zip(cut[:-1], cut[1:])}


def _slice(batch: MeasurementBatch, a: int, b: int) -> MeasurementBatch:
    """Rows a..b of a batch as a batch of its own (copies: a view would carry, and pickle, the
    whole field's tensors)."""
    return MeasurementBatch(batch.measurement_id[a:b], batch.steps[a:b].clone(),
                            batch.sun[a:b].clone(), batch.focal_spot[a:b].clone(),
                            batch.target_center[a:b].clone(), batch.target_normal[a:b].clone())


def planned_heliostats(helio: pd.DataFrame, meas: pd.DataFrame, selected: dict,
                       regimes: pd.DataFrame | None, prior: PriorScale, *, window_start=None,
                       window_days: np.ndarray | None = None,
                       days: int = 0) -> list[PlannedHeliostat]:
    """Every heliostat's design input, in ``helio``'s order.

    ``meas`` (sorted by heliostat) carries each row's split label (``split``; ``excluded``: a
    heliostat without a fit). A fitted heliostat's covariance rests on its training rows outside
    episodes in its current regime (:func:`regime_breaks`; a young regime has few) at its
    selected model's parameters; its noise scale on the rows its parameters describe. A
    heliostat without a fit rests on all its rows at its nominal geometry with the field's most
    common preset of its type, and takes the field's noise. With ``window_start``
    (``--from-existing``) only rows before the window are known, and the rows in its ``days``
    (``window_days``: each row's solar day) that are not test rows are the candidates.
    """
    span = _rows_of(meas)
    batch = MeasurementBatch.from_frame(meas)
    split = meas["split"].to_numpy()
    has_time = meas["timestamp"].notna().to_numpy()
    times = _utc_ns(meas["timestamp"])
    starts, spans = regime_breaks(regimes, {h for h, f in selected.items()
                                            if f["preset"] != f["base_preset"]})
    targets = _targets(meas) if len(meas) else {None: ([], np.zeros((0, 3)))}
    presets = _field_presets(helio, selected)
    out = []
    for _, hrow in helio.iterrows():
        hid = str(hrow["heliostat_id"])
        names, points = targets.get(hid, targets[None])
        if not names:
            continue
        a, b = span.get(hid, (0, 0))
        spec, nominal = HeliostatSpec.from_row(hrow), nominal_parameters(hrow)
        current, episode = current_regime_rows(times[a:b], starts.get(hid), spans.get(hid, []))
        before, candidates = np.ones(b - a, bool), None
        if window_start is not None:
            day = window_days[a:b]
            before = has_time[a:b] & (day < 0)
            pick = np.isfinite(day) & (day >= 0) & (day < days) & (split[a:b] != "test")
            candidates = meas.iloc[a:b][pick].assign(day=day[pick].astype(int))
        fit = selected.get(hid)
        if fit is not None:
            train = (split[a:b] == "train") & ~episode
            noise_mask = train & current if fit["preset"] != fit["base_preset"] else train
            known_mask = train & current & before
            params, free, model = fit["params"], fit["free"].numpy(), fit["preset"]
        else:
            preset = presets.get(spec.kinematic_type, FALLBACK_PRESET)
            known_mask = before & (split[a:b] != "test")
            noise_mask = np.zeros(b - a, bool)
            params = nominal
            free = preset_mask(preset, spec.actuator_type, spec.kinematic_type).numpy()
            model = f"nominal:{preset}"
        rows = _slice(batch, a, b)
        known = rows.subset(known_mask)
        noise = (known if np.array_equal(noise_mask, known_mask) else rows.subset(noise_mask)
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
