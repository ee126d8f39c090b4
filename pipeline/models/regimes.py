"""Regimes, episodes and outliers of a heliostat from its coarse residuals in time order.

Physics-free: plain functions over DataFrames of residual components [mrad] (the coarse model's
error of the mirror normal split along the target plane's horizontal and vertical axes).

Method (per heliostat)
----------------------
1. Noise. ``noise_mrad`` per component is ``1.4826 * MAD / sqrt(2)`` of the differences between
   each row and the last row of the previous measured day (UTC). Differences hardly see a step
   or an episode (only the rows right after it); taking them across days, not between
   consecutive rows, keeps bursts of rows seconds apart and the shared misfit of one day's rows
   from shrinking the noise (in real logs these differences are far smaller than the scatter
   from day to day, and a noise taken from them turns every day into a change point). With
   fewer than three such differences: 1.4826 MAD about the median.
2. Standardized signal. Each component minus its median, divided by its noise. Isolated
   outliers would otherwise become segments of their own: each value is clipped to within
   ``clip`` noise units of a centred running median of ``window`` rows (a run of at least
   ``window // 2 + 1`` rows at a new level moves the running median and is not clipped).
3. Known breaks. The renovation window of the heliostat (heliostats.parquet) cuts the series;
   each piece is segmented on its own, so a renovation is always a regime break (cause
   ``renovation``), seen or not; its ``evidence`` says whether the data show it.
4. Change points. PELT (ruptures' :class:`~ruptures.KernelCPD` with the linear kernel, i.e. the
   ``l2`` cost: a change of the mean of the standardized two-component signal) with the penalty ``penalty_factor * (d + 1) * log(n)``,
   d = 2 components: the BIC of a mean shift (d new means and one location per change point)
   for unit variance, i.e. scaled by the robust residual variance of step 1. ``penalty_factor``
   > 1 allows for residuals that are not independent (rows of one day share sun positions and a
   model misfit); its default was chosen on simulated static heliostats (benchmarks/regimes.py),
   never on real data.
5. Episodes. A segment between two others that lasts at most ``episode_max_days`` and whose
   level differs from the regime before it is an episode: the heliostat was off for a few days
   and came back (or changed again); consecutive short segments within that time are one.
6. Outliers. Rows whose robust distance from their segment's median, ``sqrt(sum(((x -
   median) / noise)^2))``, exceeds ``outlier_z``: flagged, never dropped.

:func:`detect_regimes` returns one row per segment and per outlier (the columns of
``regimes.parquet``, :data:`heliocal.pipeline.artifacts.schemas.REGIMES`).
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np
import pandas as pd

__all__ = [
    "COMPONENTS",
    "DEFAULTS",
    "detect_field",
    "detect_records",
    "detect_regimes",
    "regime_of_rows",
    "regime_arrays",
    "residual_components_mrad",
    "utc_values",
    "robust_noise_mrad",
]

#: The residual columns a detection reads [mrad].
COMPONENTS = ("residual_horizontal_mrad", "residual_vertical_mrad")

#: Defaults of :func:`detect_regimes` (module docstring, steps 2 to 6).
DEFAULTS = {"penalty_factor": 3.0, "min_size": 2, "window": 5, "clip": 5.0,
            "episode_max_days": 7.0, "outlier_z": 6.0}

_MAD_TO_SIGMA = 1.482602218505602  # 1 / Phi^-1(3/4): MAD of a normal sample -> its sigma
_NOISE_FLOOR_MRAD = 1e-6


def residual_components_mrad(offset_horizontal_m, offset_vertical_m, distance_m):
    """Residual of the mirror normal along the target plane's axes [mrad] from the spot offset.

    A beam turned by an angle a moves the spot by ``distance * a`` on the target; the normal
    turns by half the beam's angle, so the normal's component is ``offset / distance / 2``.
    """
    scale = 500.0 / np.asarray(distance_m, float)
    return np.asarray(offset_horizontal_m, float) * scale, np.asarray(offset_vertical_m, float) * scale


def robust_noise_mrad(values: np.ndarray, days=None) -> np.ndarray:
    """Robust noise per column of (n, d) values in time order (module docstring, step 1):
    ``days`` (n,) are the rows' days in any comparable form (default: every row its own day).
    NaN with fewer than 3 rows; at least 1e-6."""
    values = np.asarray(values, float)
    if len(values) < 3:
        return np.full(values.shape[1], np.nan)
    days = np.arange(len(values)) if days is None else np.asarray(days)
    prev = np.searchsorted(days, days, side="left") - 1  # last row of an earlier day
    diff = values[prev >= 0] - values[prev[prev >= 0]]
    if len(diff) >= 3:
        mad = np.median(np.abs(diff - np.median(diff, axis=0)), axis=0)
        sigma = _MAD_TO_SIGMA * mad / math.sqrt(2.0)
    else:
        sigma = _MAD_TO_SIGMA * np.median(np.abs(values - np.median(values, axis=0)), axis=0)
    return np.maximum(sigma, _NOISE_FLOOR_MRAD)


def _clipped(z: np.ndarray, window: int, clip: float) -> np.ndarray:
    """z clipped to ``clip`` around its centred running median of ``window`` rows (fewer at the
    ends: the median of the rows there, as pandas' ``rolling(center=True, min_periods=1)``)."""
    half = window // 2
    med = np.empty_like(z)
    if len(z) >= window:   # full windows: a plain median of the stacked views
        med[half:len(z) - half] = np.median(
            np.lib.stride_tricks.sliding_window_view(z, window, axis=0), axis=-1)
        ends = list(range(half)) + list(range(len(z) - half, len(z)))
    else:
        ends = range(len(z))
    for i in ends:   # the first and last rows: the rows of the window that exist
        med[i] = np.median(z[max(0, i - half):i + half + 1], axis=0)
    return med + np.clip(z - med, -clip, clip)


def _l2(z: np.ndarray) -> float:
    return float(((z - z.mean(axis=0)) ** 2).sum()) if len(z) else 0.0


def _pelt(z: np.ndarray, penalty: float, min_size: int) -> list[int]:
    """Interior break indices (start of each new segment) of PELT with an l2 cost."""
    import ruptures  # local: only fit-coarse's detection needs it

    if len(z) < 2 * min_size:
        return []
    # the linear kernel's cost is the l2 cost; KernelCPD runs PELT on it in C (ruptures.Pelt with
    # model="l2" finds the same breaks, about 1000 times slower on 300 rows)
    ends = ruptures.KernelCPD(kernel="linear", min_size=min_size).fit(z).predict(pen=penalty)
    return [int(b) for b in ends[:-1]]


def _known_breaks(times: np.ndarray, renovation: tuple | None) -> list[int]:
    """Row indices (of sorted datetime64 ``times``, UTC) where a renovation window starts and
    ends (strictly inside the series)."""
    if renovation is None:
        return []
    out = set()
    for edge in renovation:
        if edge is None or pd.isna(edge):
            continue
        edge = pd.Timestamp(edge)
        edge = edge.tz_convert("UTC").tz_localize(None) if edge.tzinfo else edge
        k = int(np.searchsorted(times, edge.to_datetime64()))
        if 0 < k < len(times):
            out.add(k)
    return sorted(out)


def detect_regimes(rows: pd.DataFrame, renovation: tuple | None = None, *,
                   penalty_factor: float = DEFAULTS["penalty_factor"],
                   min_size: int = DEFAULTS["min_size"], window: int = DEFAULTS["window"],
                   clip: float = DEFAULTS["clip"],
                   episode_max_days: float = DEFAULTS["episode_max_days"],
                   outlier_z: float = DEFAULTS["outlier_z"]) -> pd.DataFrame:
    """Segments and outliers of one heliostat (module docstring).

    Parameters
    ----------
    rows : one heliostat's rows: ``heliostat_id``, ``measurement_id``, ``timestamp`` (UTC) and
        :data:`COMPONENTS` [mrad]; rows without a timestamp or a finite residual are ignored.
    renovation : (start, end) UTC of its last renovation, or None.

    Returns
    -------
    DataFrame with the columns of ``regimes.parquet`` (empty if fewer than 3 usable rows).
    """
    return pd.DataFrame(_detect_records(rows, renovation, penalty_factor=penalty_factor,
                                        min_size=min_size, window=window, clip=clip,
                                        episode_max_days=episode_max_days,
                                        outlier_z=outlier_z), columns=_columns())


def _detect_records(rows: pd.DataFrame, renovation: tuple | None, **options) -> list[dict]:
    """:func:`detect_regimes`' rows as records."""
    return detect_records(str(rows["heliostat_id"].iloc[0]), utc_values(rows["timestamp"]),
                          rows["measurement_id"].to_numpy(),
                          np.column_stack([rows[c].to_numpy(float) for c in COMPONENTS]),
                          renovation, **options)


def detect_records(heliostat_id: str, times: np.ndarray, measurement_ids: np.ndarray,
                   residuals_mrad: np.ndarray, renovation: tuple | None = None, *,
                   penalty_factor: float = DEFAULTS["penalty_factor"],
                   min_size: int = DEFAULTS["min_size"], window: int = DEFAULTS["window"],
                   clip: float = DEFAULTS["clip"],
                   episode_max_days: float = DEFAULTS["episode_max_days"],
                   outlier_z: float = DEFAULTS["outlier_z"]) -> list[dict]:
    """:func:`detect_regimes` on arrays, its rows as records (regimes.parquet's columns but
    ``error_mrad``): ``times`` (N,) zone-less UTC datetime64 (NaT: ignored), ``measurement_ids``
    (N,), ``residuals_mrad`` (N, 2) the :data:`COMPONENTS` (non-finite: ignored). What
    ``fit-coarse`` calls per heliostat (a DataFrame per heliostat costs more than the
    detection)."""
    t_all, x_all, mid_all = times, np.asarray(residuals_mrad, float), measurement_ids
    ok = np.flatnonzero(~np.isnat(t_all) & np.isfinite(x_all).all(1))
    if len(ok) < 3:
        return []
    # time order, ties by measurement id (stable)
    order = ok[np.lexsort((mid_all[ok].astype(str), t_all[ok]))]
    times, x, mid = t_all[order], x_all[order], mid_all[order]
    stamp = lambda i: pd.Timestamp(times[i], tz="UTC")  # noqa: E731 (a few per heliostat)
    hid = str(heliostat_id)
    noise = robust_noise_mrad(x, times.astype("datetime64[D]"))
    z = _clipped((x - np.median(x, axis=0)) / noise, window, clip)
    penalty = penalty_factor * (x.shape[1] + 1) * math.log(len(x))
    known = _known_breaks(times, renovation)
    bounds = [0, *known, len(x)]
    breaks: dict[int, str] = {k: "renovation" for k in known}
    for a, b in zip(bounds[:-1], bounds[1:]):
        for k in _pelt(z[a:b], penalty, min_size):
            breaks.setdefault(a + k, "detected")
    segments = _merge_episodes(times, [0, *sorted(breaks)], [*sorted(breaks), len(x)],
                               episode_max_days, set(known))
    out, level, level_n, regime, last_kind = [], None, 0, 0, "regime"
    noise_mrad = float(noise.mean())
    for k, (s, e, episode) in enumerate(segments):
        center = np.median(x[s:e], axis=0)
        # a short segment at the level of the regime before it is the heliostat back to normal
        # between two episodes, not an episode
        episode = episode and (level is None or _differs(center, level, noise, e - s, level_n,
                                                         penalty))
        if k > 0 and not episode:
            # a new regime, except when the heliostat comes back to its level after an episode
            if last_kind != "episode" or _differs(center, level, noise, e - s, level_n, penalty):
                regime += 1
        if not episode:
            level, level_n = center, e - s
        last_kind = "episode" if episode else "regime"
        if k:
            p = segments[k - 1][0]
            previous = np.median(x[p:s], axis=0)
            step = float(np.linalg.norm(center - previous))
            evidence = (_l2(z[p:e]) - _l2(z[p:s]) - _l2(z[s:e])) / penalty
        else:
            step = evidence = float("nan")
        out.append({
            "heliostat_id": hid, "kind": "episode" if episode else "regime", "regime": regime,
            "start": stamp(s), "end": stamp(e - 1),
            "cause": "start" if k == 0 else breaks[s], "n_rows": int(e - s),
            "measurement_id": None,
            "center_horizontal_mrad": float(center[0]), "center_vertical_mrad": float(center[1]),
            "step_mrad": step, "evidence": float(evidence), "noise_mrad": noise_mrad})
        if episode:  # an episode's rows are all off: flagged as the episode, not one by one
            continue
        dist = np.sqrt((((x[s:e] - center) / noise) ** 2).sum(axis=1))
        for j in np.flatnonzero(dist > outlier_z):
            i = s + int(j)
            out.append({
                "heliostat_id": hid, "kind": "outlier", "regime": regime,
                "start": stamp(i), "end": stamp(i), "cause": "outlier", "n_rows": 1,
                "measurement_id": str(mid[i]),
                "center_horizontal_mrad": float(x[i, 0]), "center_vertical_mrad": float(x[i, 1]),
                "step_mrad": float(np.linalg.norm(x[i] - center)), "evidence": float(dist[j]),
                "noise_mrad": noise_mrad})
    return out


def _merge_episodes(times: np.ndarray, starts: list[int], ends: list[int], max_days: float,
                    known: set[int]) -> list[tuple[int, int, bool]]:
    """(start, end, is_episode) of the segments, consecutive short interior segments (at most
    ``max_days`` from their first to their last row, ``times`` datetime64) merged into one
    episode: an episode's residuals move with the sun, so PELT may cut it in pieces. A
    renovation break is kept."""
    day = np.timedelta64(1, "D")
    days = lambda a, b: (times[b] - times[a]) / day  # noqa: E731
    short = [0 < k < len(starts) - 1 and days(s, e - 1) <= max_days
             for k, (s, e) in enumerate(zip(starts, ends))]
    out: list[tuple[int, int, bool]] = []
    for s, e, is_short in zip(starts, ends, short):
        if (is_short and out and out[-1][2] and s not in known
                and days(out[-1][0], e - 1) <= max_days):
            out[-1] = (out[-1][0], e, True)
        else:
            out.append((s, e, is_short))
    return out


def _columns() -> list[str]:
    """regimes.parquet's columns this module fills (fit-coarse adds ``error_mrad``)."""
    from ..artifacts.schemas import REGIMES

    return [c for c in REGIMES.column_names() if c != "error_mrad"]


def _differs(a: np.ndarray, b: np.ndarray, noise: np.ndarray, n_a: int, n_b: int,
             penalty: float) -> bool:
    """Do two levels (medians) differ by more than the penalty allows (l2 gain of one break)?"""
    gain = (((a - b) / noise) ** 2).sum() * n_a * n_b / (n_a + n_b)
    return bool(gain > penalty)


def detect_field(residuals: pd.DataFrame, renovations: Mapping[str, tuple] | None = None,
                 **options) -> pd.DataFrame:
    """:func:`detect_regimes` for every heliostat of ``residuals``; ``renovations`` maps a
    heliostat id to its (start, end) renovation window."""
    renovations = renovations or {}
    options = {**DEFAULTS, **options}
    records = [r for hid, g in residuals.groupby("heliostat_id", sort=True)
               for r in _detect_records(g, renovations.get(str(hid)), **options)]
    return pd.DataFrame(records, columns=_columns())


def _naive(times) -> pd.Series:
    """UTC times without a zone (datetime64, for searchsorted)."""
    return pd.to_datetime(pd.Series(times), utc=True).dt.tz_localize(None)


def utc_values(times) -> np.ndarray:
    """UTC times (anything pandas reads as times; naive ones are taken as UTC) as zone-less
    datetime64 values, NaT where missing. A zone-aware column is read as it is (its values are
    UTC already), which is a hundred times faster than converting it."""
    if isinstance(times, pd.Series) and isinstance(times.dtype, pd.DatetimeTZDtype):
        return times.array.tz_convert(None).to_numpy()
    if isinstance(times, np.ndarray) and np.issubdtype(times.dtype, np.datetime64):
        return times   # zone-less datetime64: UTC by this module's convention
    return _naive(times).to_numpy()


def regime_of_rows(regimes: pd.DataFrame, heliostat_id: str, timestamps: pd.Series) -> pd.DataFrame:
    """Per row (timestamps of one heliostat): ``regime`` (number) and ``episode`` (True inside a
    detected episode's time span) from regimes.parquet's rows of that heliostat. Rows before the
    first segment get regime 0; rows without a timestamp get the latest regime."""
    regime, episode = regime_arrays(regimes, heliostat_id, timestamps)
    return pd.DataFrame({"regime": regime, "episode": episode}, index=timestamps.index)


def regime_arrays(regimes: pd.DataFrame, heliostat_id: str,
                  timestamps) -> tuple[np.ndarray, np.ndarray]:
    """:func:`regime_of_rows` as two arrays (regime int64, episode bool), without the frame."""
    kinds = regimes["kind"].to_numpy()
    mine = (regimes["heliostat_id"].to_numpy() == heliostat_id) & (kinds != "outlier")
    starts = utc_values(regimes["start"])[mine]
    order = np.argsort(starts, kind="stable")
    starts, kinds = starts[order], kinds[mine][order]
    ends = utc_values(regimes["end"])[mine][order]
    numbers = regimes["regime"].to_numpy(np.int64)[mine][order]
    t = utc_values(timestamps)
    regime = np.zeros(len(t), dtype=np.int64)
    episode = np.zeros(len(t), dtype=bool)
    if len(starts):
        k = np.searchsorted(starts, t, side="right") - 1
        k = np.where(np.isnat(t), len(starts) - 1, np.maximum(k, 0))
        regime = numbers[k]
        episode = (kinds[k] == "episode") & (t <= ends[k])
    return regime, episode
