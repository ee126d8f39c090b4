"""Training/validation/test splits of each heliostat's measurements (stage ``split-knn``).

The default method is the kNN split of Lewen et al. (paper 000, section 3.2, after Pargmann et
al. 2023): per heliostat, every measurement gets the mean distance to its ``k`` nearest other
measurements in sun position (azimuth, elevation); sorted by that distance in descending order,
the first ``n_test`` are the test set, the next ``n_val`` the validation set and the rest the
training set. A training-size limit drops the training rows with the *smallest* kNN distance
first, as the paper does. Test accuracies of such a split are conservative: the test points are
the ones farthest from everything else.

For comparison the module also implements a seeded random split, a chronological split (paper
002 trains on the earlier part) and PAINT's four benchmark splits (``azimuth``, ``solstice``,
``balanced``, ``high-variance``; ARTIST-Association/PAINT, ``paint/data/dataset_splits.py``).
How their train/validation/test roles map onto ours is documented in ``docs/split.md``; in short,
for every method the test set is the held-out block that is hardest under the method's own
criterion, validation is the next block, and the rest trains.

Whatever the method, every row gets its kNN distance (with the run's ``k`` and metric), its rank
by that distance and its distance to the nearest training measurement, so splits made by
different methods can be compared on the same scale. All distances are in degrees: either the
Euclidean distance in the (azimuth, elevation) plane (``euclidean``, the paper's choice) or the
great-circle angle between the two sun vectors (``great-circle``, free of the azimuth distortion
near the zenith).
"""

from __future__ import annotations

import logging
import warnings
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..artifacts.incremental import (carry_over_unchanged, field_key, heliostat_digests,
                                     plan_increment, reused_rows)
from ..artifacts.manifests import current_transaction
from ..artifacts.store import read_artifact, write_artifact
from ..errors import FitError, InputError, ParameterError, check_choice, check_int
from ..artifacts.schemas import MEASUREMENTS
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir
from ..artifacts.schemas import SPLIT
from ..vocabulary import SplitMethod, SplitMetric
from ..runtime.process_state import restores_process_state
from .rerun import (MIN_TRAIN, required_measurements, requirement_text, split_kept_summary,
                    split_options)

__all__ = [
    "METHODS",
    "METRICS",
    "SPLIT_LABELS",
    "knn_distance_deg",
    "split_measurements",
    "restrict_training",
    "required_measurements",
    "summarize_split",
    "run_split",
    "time_split_labels",
    "TIME_SPLIT_LABELS",
]

#: Split methods; ``knn`` is the default (paper 000, section 3.2).
METHODS = SplitMethod.values()
#: Distance metrics in sun position.
METRICS = SplitMetric.values()
#: Values of the ``split`` column.
SPLIT_LABELS = ("train", "validation", "test", "unused")
#: Values of the ``time_split`` column (missing where a heliostat has no time split).
TIME_SPLIT_LABELS = ("train", "validation", "test", "unused")

_FUNC = "split_knn"

log = logging.getLogger("heliocal.split")



_INPUT_COLUMNS = ["heliostat_id", "measurement_id", "timestamp", "sun_azimuth_deg",
                  "sun_elevation_deg"]


# --------------------------------------------------------------------------------------------
# distances
# --------------------------------------------------------------------------------------------
def _features(az_deg, el_deg, metric: str) -> tuple[np.ndarray, dict]:
    az = np.asarray(az_deg, dtype=float).reshape(-1)
    el = np.asarray(el_deg, dtype=float).reshape(-1)
    if az.shape != el.shape:
        raise ValueError(f"azimuth and elevation differ in length ({az.size} vs {el.size})")
    if metric == "euclidean":
        # kd-tree: exact sqrt of summed squares (no Gram-matrix rounding), independent of order.
        return np.column_stack([az, el]), {"metric": "euclidean", "algorithm": "kd_tree"}
    # The haversine metric takes (latitude, longitude) in radians: elevation is the latitude
    # and azimuth the longitude of the sun on the unit sphere, so the haversine distance is the
    # angle between the sun vectors whatever the azimuth's zero and sense.
    return (np.column_stack([np.radians(el), np.radians(az)]),
            {"metric": "haversine", "algorithm": "ball_tree"})


def _to_deg(dist: np.ndarray, metric: str) -> np.ndarray:
    return np.degrees(dist) if metric == "great-circle" else dist


def knn_distance_deg(az_deg, el_deg, k: int = 3, metric: str = "euclidean") -> np.ndarray:
    """Mean distance of each sun position to its ``k`` nearest *other* positions.

    Paper 000, section 3.2: the kNN distance with k = 1, 2 or 3 in (azimuth, elevation).

    Parameters
    ----------
    az_deg : sun azimuths [°].
    el_deg : sun elevations [°], same length.
    k : number of neighbours, 1, 2 or 3 [1].
    metric : ``euclidean`` (distance in the azimuth-elevation plane [°], the paper's) or
        ``great-circle`` (angle between the sun vectors [°]).

    Returns
    -------
    Array of the mean distances [°], one per position. A position is never its own neighbour;
    a duplicate position is (at distance 0).

    Raises
    ------
    ParameterError : ``k`` or ``metric`` is not allowed, or there are not more than ``k``
        positions.
    """
    k = check_int(k, "k", _FUNC, 1, 3)
    metric = check_choice(metric, "metric", _FUNC, METRICS)
    x, nn_kw = _features(az_deg, el_deg, metric)
    if len(x) <= k:
        raise ParameterError(f"the kNN distance with k={k} needs at least {k + 1} sun positions; "
                             f"got {len(x)}")
    from sklearn.neighbors import NearestNeighbors  # here: a kept split never loads sklearn

    nn = NearestNeighbors(n_neighbors=k, **nn_kw).fit(x)
    dist, _ = nn.kneighbors()  # X=None: each point's neighbours without the point itself
    return _to_deg(dist, metric).mean(axis=1)


def _nearest_distance(x_from: np.ndarray, x_to: np.ndarray, nn_kw: dict, metric: str,
                      same: np.ndarray | None) -> np.ndarray:
    """Distance [°] from each row of ``x_from`` to the nearest row of ``x_to``.

    ``same[i]`` is the index into ``x_to`` of row i itself (or -1): that row is skipped.
    """
    n_nb = min(2, len(x_to))
    from sklearn.neighbors import NearestNeighbors

    nn = NearestNeighbors(n_neighbors=n_nb, **nn_kw).fit(x_to)
    dist, idx = nn.kneighbors(x_from)
    out = dist[:, 0].copy()
    if same is not None:
        # A training row's first neighbour may be itself or a duplicate at distance 0: either
        # way, the nearest *other* training row is at distance dist[:, 1] when idx[:, 0] is the
        # row itself, and at dist[:, 0] (= 0, the duplicate) otherwise.
        self_first = idx[:, 0] == same
        out[self_first] = dist[self_first, 1]
    return _to_deg(out, metric)


def _nearest_train(az: np.ndarray, el: np.ndarray, is_train: np.ndarray, metric: str) -> np.ndarray:
    x, nn_kw = _features(az, el, metric)
    train_idx = np.flatnonzero(is_train)
    same = np.full(len(x), -1)
    same[train_idx] = np.arange(train_idx.size)
    return _nearest_distance(x, x[train_idx], nn_kw, metric, same)


# --------------------------------------------------------------------------------------------
# orderings of the methods
# --------------------------------------------------------------------------------------------
def _order_by(key: np.ndarray, ids: np.ndarray, descending: bool) -> np.ndarray:
    """Positions sorted by ``key`` (descending or ascending), ties by ascending id."""
    frame = pd.DataFrame({"key": key, "id": ids})
    return frame.sort_values(["key", "id"], ascending=[not descending, True],
                             kind="mergesort").index.to_numpy()


def _rng(seed: int, heliostat_id: str) -> np.random.Generator:
    # One stream per heliostat, so a heliostat's split does not depend on which others exist.
    return np.random.default_rng([seed, zlib.crc32(str(heliostat_id).encode())])


def _summer_solstice_distance_s(ts: pd.Series) -> np.ndarray:
    """Seconds to the nearest 21 June 12:00 UTC (PAINT's definition of the solstice)."""
    ts = pd.to_datetime(pd.Series(ts).reset_index(drop=True), utc=True)
    epoch = pd.Timestamp("1970-01-01", tz="UTC")
    t = (ts - epoch).dt.total_seconds().to_numpy()
    years = ts.dt.year.to_numpy()
    best = np.full(len(ts), np.inf)
    for dy in (-1, 0, 1):
        sol = pd.to_datetime(pd.DataFrame({"year": years + dy, "month": 6, "day": 21,
                                           "hour": 12}), utc=True)
        best = np.minimum(best, np.abs(t - (sol - epoch).dt.total_seconds().to_numpy()))
    return best


def _stratified_draw(labels: np.ndarray, available: np.ndarray, count: int,
                     rng: np.random.Generator) -> list[int]:
    """Draw ``count`` rows round-robin over clusters: one per cluster per round, random order."""
    picked: list[int] = []
    available = available.copy()
    clusters = np.unique(labels)
    while len(picked) < count:
        progressed = False
        for c in rng.permutation(clusters):
            members = np.flatnonzero(available & (labels == c))
            if members.size == 0:
                continue
            i = int(rng.choice(members))
            picked.append(i)
            available[i] = False
            progressed = True
            if len(picked) == count:
                break
        if not progressed:
            break
    return picked


def _held_out_order(g: pd.DataFrame, method: str, n_test: int, n_val: int, seed: int,
                    knn_d: np.ndarray, knn3_euclid: np.ndarray | None) -> np.ndarray:
    """Row positions in the order rows are held out: the first n_test are test, then n_val
    validation; positions not listed (or after them) train."""
    ids = g["measurement_id"].to_numpy(dtype=object)
    hid = g["heliostat_id"].iloc[0]
    if method == "knn":
        return _order_by(knn_d, ids, descending=True)
    if method == "high-variance":
        return _order_by(knn3_euclid, ids, descending=True)
    if method == "random":
        return _rng(seed, hid).permutation(len(g))
    if method == "time":
        epoch = pd.Timestamp("1970-01-01", tz="UTC")
        t = (pd.to_datetime(g["timestamp"], utc=True) - epoch).dt.total_seconds().to_numpy()
        # latest first: the last n_test are test, the n_val before them validation
        return _order_by(t, ids, descending=True)
    if method == "azimuth":
        return _order_by(g["sun_azimuth_deg"].to_numpy(float), ids, descending=True)
    if method == "solstice":
        return _order_by(_summer_solstice_distance_s(g["timestamp"]), ids, descending=False)
    if method == "balanced":
        n_clusters = max(n_test, n_val)
        if n_clusters == 0:
            return np.array([], dtype=int)
        from sklearn.cluster import KMeans

        rng = _rng(seed, hid)
        x = g[["sun_azimuth_deg", "sun_elevation_deg"]].to_numpy(float)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # fewer distinct points than clusters: still valid
            labels = KMeans(n_clusters=n_clusters, n_init=10,
                            random_state=int(rng.integers(2**31 - 1))).fit_predict(x)
        available = np.ones(len(g), dtype=bool)
        test = _stratified_draw(labels, available, n_test, rng)
        available[test] = False
        val = _stratified_draw(labels, available, n_val, rng)
        return np.array(test + val, dtype=int)
    raise AssertionError(method)  # pragma: no cover - validated by check_choice


def time_split_labels(g: pd.DataFrame, n_test: int, n_val: int, n_train: int | None,
                      knn_d: np.ndarray) -> tuple[np.ndarray, str | None]:
    """The forward-in-time split of one heliostat, beside its selection split (issue 17).

    The latest ``n_test`` timed rows are ``test``, the ``n_val`` before them ``validation``, the
    earlier rows ``train`` (with ``n_train``: the kNN rule of :func:`restrict_training` among
    them, the rest ``unused``), i.e. the sizes of the kNN split. A row without timestamp cannot
    be placed in time and gets no label (``None``); nor does any row of a heliostat with fewer
    than ``n_test + n_val + max(n_train, 2)`` timed rows (then the reason is returned as text).

    Parameters
    ----------
    g : one heliostat's rows sorted by ``measurement_id`` (columns ``measurement_id`` and,
        if present, ``timestamp``).
    knn_d : the rows' kNN distances [deg] (for ``n_train``).

    Returns
    -------
    (labels, why_not): object array of labels or ``None`` per row, and ``None`` or why the
    heliostat has no time split.
    """
    labels = np.full(len(g), None, dtype=object)
    if "timestamp" not in g.columns:
        return labels, "the measurements have no timestamps"
    timed = g["timestamp"].notna().to_numpy()
    need = n_test + n_val + (MIN_TRAIN if n_train is None else n_train)
    if timed.sum() < need:
        return labels, f"{int(timed.sum())} of its measurements have a timestamp, the time split needs {need}"
    idx = np.flatnonzero(timed)
    sub = g.iloc[idx]
    epoch = pd.Timestamp("1970-01-01", tz="UTC")
    t = (pd.to_datetime(sub["timestamp"], utc=True) - epoch).dt.total_seconds().to_numpy()
    order = idx[_order_by(t, sub["measurement_id"].to_numpy(dtype=object), descending=True)]
    labels[idx] = "train"
    labels[order[:n_test]] = "test"
    labels[order[n_test:n_test + n_val]] = "validation"
    if n_train is not None:
        cand = order[n_test + n_val:]
        ranked = cand[_order_by(knn_d[cand], g["measurement_id"].to_numpy(dtype=object)[cand],
                                True)]
        labels[ranked[n_train:]] = "unused"
    return labels, None


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------
def split_measurements(measurements: pd.DataFrame, *, method: str = "knn", k: int = 3,
                       n_test: int = 30, n_val: int = 20, n_train: int | None = None,
                       metric: str = "euclidean", seed: int = 0
                       ) -> tuple[pd.DataFrame, list[tuple[str, int]]]:
    """Split each heliostat's measurements into train, validation, test (and unused) sets.

    Parameters
    ----------
    measurements : table with ``heliostat_id``, ``measurement_id``, ``sun_azimuth_deg`` [°],
        ``sun_elevation_deg`` [°], and ``timestamp`` (UTC) for methods ``time`` and
        ``solstice``.
    method : one of :data:`METHODS` (see the module docstring and docs/split.md).
    k : neighbours of the kNN distance, 1, 2 or 3 (paper 000, section 3.2).
    n_test : test rows per heliostat (paper: 30).
    n_val : validation rows per heliostat (paper: 20).
    n_train : keep only this many training rows, those with the largest kNN distance; the
        others become ``unused`` (paper: smallest kNN distance dropped first). ``None``: all.
    metric : ``euclidean`` or ``great-circle``, for every distance column.
    seed : seed of the random steps (methods ``random`` and ``balanced``).

    Returns
    -------
    (table matching :data:`SPLIT`, skipped) where ``skipped`` lists ``(heliostat_id, count)`` of
    the heliostats with fewer than :func:`required_measurements` measurements, which are left
    out of the table.

    Raises
    ------
    ParameterError : an option is outside its allowed values.
    InputError : required columns are missing, a measurement id repeats within a heliostat, or
        a time-based method meets measurements without timestamp.
    FitError : no heliostat has enough measurements.
    """
    opts = split_options(method, k, n_test, n_val, n_train, metric, seed)
    method, k, n_test, n_val, n_train, metric, seed = (
        opts[key] for key in ("method", "k", "n_test", "n_val", "n_train", "metric", "seed"))
    needed = ["heliostat_id", "measurement_id", "sun_azimuth_deg", "sun_elevation_deg"]
    if method in ("time", "solstice"):
        needed.append("timestamp")
    absent = [c for c in needed if c not in measurements.columns]
    if absent:
        raise InputError(f"the measurements lack columns {absent}; rerun `heliocal ingest`")
    if measurements.empty:
        raise FitError("there are no measurements to split; check the output of `heliocal ingest`")

    df = measurements[[c for c in _INPUT_COLUMNS if c in measurements.columns]].copy()
    df["heliostat_id"] = df["heliostat_id"].astype(str).astype(object)
    df["measurement_id"] = df["measurement_id"].astype(str).astype(object)
    dup = df.duplicated(["heliostat_id", "measurement_id"])
    if dup.any():
        first = df.loc[dup].iloc[0]
        raise InputError(f"measurement id {first['measurement_id']!r} occurs more than once for "
                         f"heliostat {first['heliostat_id']}; rerun `heliocal ingest`")

    need = required_measurements(k, n_test, n_val, n_train)
    skipped: list[tuple[str, int]] = []
    parts = []
    for hid, g in df.groupby("heliostat_id", sort=True):
        if len(g) < need:
            skipped.append((str(hid), int(len(g))))
            continue
        g = g.sort_values("measurement_id", kind="mergesort").reset_index(drop=True)
        if method in ("time", "solstice"):
            untimed = int(g["timestamp"].isna().sum())
            if len(g) - untimed < n_test + n_val:
                raise InputError(
                    f"method {method!r} needs timestamps for the {n_test} test and {n_val} "
                    f"validation measurements, but only {len(g) - untimed} of heliostat {hid}'s "
                    f"{len(g)} have one; choose another --method")
            if untimed:
                # NaN keys sort last, so these rows are never held out: they stay training
                # candidates (their time is unknown, so they cannot be placed in a time split).
                log.warning("heliostat %s: %d measurement(s) without timestamp (ids %s) cannot "
                            "be held out by method %r and stay training candidates", hid,
                            untimed, ", ".join(g.loc[g["timestamp"].isna(), "measurement_id"]),
                            method)
        az = g["sun_azimuth_deg"].to_numpy(float)
        el = g["sun_elevation_deg"].to_numpy(float)
        knn_d = knn_distance_deg(az, el, k, metric)
        knn3 = knn_distance_deg(az, el, 3, "euclidean") if method == "high-variance" else None
        order = _held_out_order(g, method, n_test, n_val, seed, knn_d, knn3)
        time_label, why_not = time_split_labels(g, n_test, n_val, n_train, knn_d)
        if why_not:
            log.warning("heliostat %s has no time split (%s): its forward-in-time errors are n/a",
                        hid, why_not)
        label = np.full(len(g), "train", dtype=object)
        label[order[:n_test]] = "test"
        label[order[n_test:n_test + n_val]] = "validation"
        rank = np.empty(len(g), dtype=np.int64)
        rank[_order_by(knn_d, g["measurement_id"].to_numpy(dtype=object), True)] = np.arange(len(g))
        parts.append(pd.DataFrame({
            "heliostat_id": g["heliostat_id"], "measurement_id": g["measurement_id"],
            "split": label, "time_split": time_label, "knn_distance_deg": knn_d,
            "knn_rank": rank,
            "nearest_train_distance_deg": np.nan, "method": method, "metric": metric,
            "sun_azimuth_deg": az, "sun_elevation_deg": el,
        }))

    if not parts:
        counts = ", ".join(f"{h} has {c}" for h, c in skipped)
        raise FitError(
            f"no heliostat has enough measurements for this split: each needs at least "
            f"{requirement_text(k, n_test, n_val, n_train)}, but {counts}; lower --n-test, "
            "--n-val or --n-train")
    table = pd.concat(parts, ignore_index=True)
    return restrict_training(table, n_train), skipped


def restrict_training(split_df: pd.DataFrame, n_train: int | None) -> pd.DataFrame:
    """Keep ``n_train`` training rows per heliostat: those with the largest kNN distance.

    The training candidates are the rows marked ``train`` or ``unused`` (``unused`` always
    means "a training row dropped by a size limit"), so restricting is idempotent and a larger
    ``n_train`` restores dropped rows. Candidates are ranked by ``knn_distance_deg``
    (descending, ties by ``measurement_id``) and all but the first ``n_train`` become
    ``unused`` (paper 000, section 3.2: "measurements with the smallest kNN were excluded from
    training"). ``nearest_train_distance_deg`` is recomputed for every row with the table's
    ``metric``. Used by ``split-knn --n-train`` and by the training-size sweep.

    Parameters
    ----------
    split_df : a table matching :data:`SPLIT`.
    n_train : training rows to keep per heliostat (at least 2), or ``None`` for all candidates.

    Raises
    ------
    ParameterError : ``n_train`` is not an int >= 2.
    FitError : a heliostat has fewer than ``n_train`` training candidates (message names them).
    """
    if n_train is not None:
        n_train = check_int(n_train, "n_train", "restrict_training", MIN_TRAIN)
    out = split_df.copy().reset_index(drop=True)
    candidate = out["split"].isin(["train", "unused"]).to_numpy()
    split = out["split"].to_numpy(dtype=object).copy()
    split[candidate] = "train"
    short = []
    for _, idx in out.groupby("heliostat_id", sort=True).indices.items():
        cand = idx[candidate[idx]]
        if n_train is not None:
            if cand.size < n_train:
                short.append((out["heliostat_id"].iloc[idx[0]], int(cand.size)))
                continue
            sub = out.iloc[cand]
            ranked = cand[_order_by(sub["knn_distance_deg"].to_numpy(float),
                                    sub["measurement_id"].to_numpy(dtype=object), True)]
            split[ranked[n_train:]] = "unused"
    if short:
        names = ", ".join(f"{h} has {c}" for h, c in short)
        raise FitError(f"too few training candidates for n_train={n_train}: {names}; lower "
                       "n_train or leave those heliostats out")
    out["split"] = split
    is_train = split == "train"
    near = np.empty(len(out))
    for _, idx in out.groupby("heliostat_id", sort=True).indices.items():
        metric = out["metric"].iloc[idx[0]]
        g = out.iloc[idx]
        if is_train[idx].sum() < 2:
            raise FitError(f"heliostat {g['heliostat_id'].iloc[0]} has fewer than 2 training rows; "
                           "its nearest-training distances are undefined")
        near[idx] = _nearest_train(g["sun_azimuth_deg"].to_numpy(float),
                                   g["sun_elevation_deg"].to_numpy(float), is_train[idx], metric)
    out["nearest_train_distance_deg"] = near
    return out


def _per_set(split_df: pd.DataFrame, labels: str, column: str | None = None) -> dict:
    """``{(heliostat_id, set): value}`` over the sets of the column ``labels``: the row count,
    or the mean of ``column`` (NaN where all its values are missing)."""
    grouped = split_df.groupby(["heliostat_id", labels], sort=False, observed=True)
    return (grouped.size() if column is None else grouped[column].mean()).to_dict()


def summarize_split(split_df: pd.DataFrame) -> list[dict[str, Any]]:
    """Per heliostat: counts per set, mean kNN distance per set [°], and mean distance from
    the test rows to the nearest training row [°] (``None`` for an empty set)."""
    counts = _per_set(split_df, "split")
    knn = _per_set(split_df, "split", "knn_distance_deg")
    nearest = _per_set(split_df, "split", "nearest_train_distance_deg")
    timed = "time_split" in split_df.columns
    tcounts = _per_set(split_df, "time_split") if timed else {}
    sizes = split_df["heliostat_id"].value_counts(sort=False).to_dict()

    def mean(table: dict, hid, s: str) -> float | None:
        return float(table[hid, s]) if (hid, s) in table else None

    rows = []
    for hid in sorted(split_df["heliostat_id"].unique()):
        in_time = {s: int(tcounts.get((hid, s), 0)) for s in TIME_SPLIT_LABELS}
        rows.append({
            "heliostat_id": str(hid),
            "n_measurements": int(sizes[hid]),
            "counts": {s: int(counts.get((hid, s), 0)) for s in SPLIT_LABELS},
            # the forward-in-time split beside it; None: the heliostat has none (no timestamps)
            "time_split_counts": in_time if sum(in_time.values()) else None,
            "mean_knn_distance_deg": {s: mean(knn, hid, s)
                                      for s in ("train", "validation", "test")},
            "mean_test_to_train_distance_deg": mean(nearest, hid, "test"),
            "mean_validation_to_train_distance_deg": mean(nearest, hid, "validation"),
        })
    return rows


@locks_workdir("split-knn")
@stage_transaction("split-knn")
@restores_process_state
def run_split(workdir: str | Path, *, method: str = "knn", k: int = 3, n_test: int = 30,
              n_val: int = 20, n_train: int | None = None, metric: str = "euclidean",
              seed: int = 0, incremental: bool = False) -> dict[str, Any]:
    """Stage ``split-knn``: read ``measurements.parquet``, split, write ``split.parquet``.

    Every heliostat's split depends on its own rows only (the random methods draw from a stream
    per heliostat), so with ``incremental`` only heliostats whose rows changed since the last
    committed run are split again and the others' rows are taken from the previous split.parquet
    (:mod:`heliocal.pipeline.artifacts.incremental`); the table equals a full run's.

    Returns a JSON-able summary: the options, the artifact path, per heliostat the output of
    :func:`summarize_split`, and the skipped heliostats with their counts and the requirement.
    """
    options = split_options(method, k, n_test, n_val, n_train, metric, seed)
    k, n_test, n_val, n_train = (options[key] for key in ("k", "n_test", "n_val", "n_train"))
    txn = current_transaction(workdir, "split-knn")
    if incremental and carry_over_unchanged(txn, options):
        return split_kept_summary(workdir, options)
    measurements = read_artifact(workdir, MEASUREMENTS, columns=_INPUT_COLUMNS)
    plan = plan_increment(txn,
                          field_key("split-knn", options, [measurements]),
                          heliostat_digests([measurements]), incremental)
    table, skipped = _split_increment(workdir, measurements, plan, options)
    path = write_artifact(table, workdir, SPLIT, stage="split-knn", options=options,
                          seed=options["seed"])
    return {
        "artifact": str(path),
        **options,
        "required_measurements": required_measurements(k, n_test, n_val, n_train),
        "requirement": requirement_text(k, n_test, n_val, n_train),
        "heliostats": summarize_split(table),
        "skipped": [{"heliostat_id": h, "n_measurements": c} for h, c in skipped],
        "incremental": plan.summary(),
    }


def _split_increment(workdir, measurements: pd.DataFrame, plan, options: dict
                     ) -> tuple[pd.DataFrame, list[tuple[str, int]]]:
    """The split of the heliostats ``plan`` computes, beside the previous split's rows of those it
    reuses (a reused heliostat that the previous run skipped is skipped again: same rows)."""
    if not plan.partial:
        return split_measurements(measurements, **options)
    previous = read_artifact(workdir, SPLIT)
    kept = reused_rows(previous, plan.reuse)
    ids = measurements["heliostat_id"].astype(str)
    counts = ids.value_counts()
    split_before = set(kept["heliostat_id"])    # once, not once per reused heliostat
    skipped = [(h, int(counts[h])) for h in plan.reuse if h not in split_before]
    need = required_measurements(options["k"], options["n_test"], options["n_val"],
                                 options["n_train"])
    todo = [h for h in plan.compute if counts[h] >= need]
    skipped += [(h, int(counts[h])) for h in plan.compute if counts[h] < need]
    parts = [kept]
    if todo:
        fresh, _ = split_measurements(measurements[ids.isin(set(todo)).to_numpy()], **options)
        parts.append(fresh)
    if not sum(len(p) for p in parts):
        return split_measurements(measurements, **options)  # raises its FitError
    return pd.concat(parts, ignore_index=True), sorted(skipped)
