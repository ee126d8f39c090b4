"""Accuracy regression check: compare a run's metrics.json with a committed baseline.

:func:`compare_metrics` lists every difference that counts as a regression, one readable line
each; an empty list means the run is within tolerance. What is checked (see docs/report.md):

* **counts match exactly**: heliostats, measurements, rejected rows (per reason), the split
  counts per heliostat, and ``n`` per heliostat, model and split;
* **every model of the baseline is still there** (new models in the current run are fine);
* **errors may not grow beyond tolerance** on the checked splits (validation and test): the mean
  error_mrad by more than ``max(mean_rel * baseline, mean_abs_mrad)`` (default 5 % or 0.05 mrad),
  the median and 95th percentile by more than ``max(quantile_rel * baseline, quantile_abs_mrad)``
  (default 10 % or 0.10 mrad), a quantile's widened by ``sqrt(5 / k)`` when only k < 5 rows of
  the split lie beyond it (:meth:`Tolerances.allowed`); this holds per heliostat for every model and for the *selected*
  model (whose name may change: a different preset or hybrid winning is not by itself a
  regression, its accuracy is what is compared). Lower errors always pass.

Versions, git revision, workdir and input hashes are not compared.

Command line::

    python -m heliocal.pipeline.report.regression CURRENT_METRICS_JSON BASELINE_METRICS_JSON

exits 0 when within tolerance, 1 with the differences on stderr, 2 when a file is unreadable.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Mapping

__all__ = ["Tolerances", "DEFAULT_TOLERANCES", "compare_metrics", "load_metrics", "main", "format_report"]


@dataclass(frozen=True)
class Tolerances:
    """How much worse than the baseline a run may be before it counts as a regression.

    An error statistic ``x`` with baseline ``b`` regresses when ``x - b > max(rel * b, abs)``.
    """

    mean_rel: float = 0.05  #: relative growth allowed for the mean error [1]
    mean_abs_mrad: float = 0.05  #: absolute growth always allowed for the mean error [mrad]
    quantile_rel: float = 0.10  #: relative growth allowed for median and p95 [1]
    quantile_abs_mrad: float = 0.10  #: absolute growth always allowed for median and p95 [mrad]
    #: rows beyond a quantile from which on its tolerance is ``quantile_rel``/``quantile_abs_mrad``
    tail_rows: float = 5.0
    splits: tuple[str, ...] = ("validation", "test")  #: splits whose errors are checked

    def allowed(self, stat: str, baseline: float, n: int | None = None) -> float:
        """Growth of ``stat`` allowed over ``baseline`` [mrad] on a split of ``n`` rows.

        A quantile rests on the k = n (1 - q) rows beyond it, and its sampling error grows as
        1 / sqrt(k): from :attr:`tail_rows` rows on the quantile tolerance holds as it is (the
        median from 10 rows, p95 from 100); below, it is widened by sqrt(tail_rows / k). The
        p95 of 20 validation rows is one row's error (k = 1, 2.24x the base tolerance): a
        network trained on another CPU, whose rounding moves its trajectory as another seed
        does (docs/hybrid.md, "Training precision"), moved that one row of sample_data's BH35
        by 11 % while its mean moved by 1.5 %."""
        if stat == "mean_error_mrad":
            return max(self.mean_rel * abs(baseline), self.mean_abs_mrad)
        base = max(self.quantile_rel * abs(baseline), self.quantile_abs_mrad)
        beyond = None if not n else n * (1.0 - _QUANTILES[stat])
        return base if beyond is None else base * max(1.0, math.sqrt(self.tail_rows / beyond))


DEFAULT_TOLERANCES = Tolerances()
_STATS = ("mean_error_mrad", "median_error_mrad", "p95_error_mrad")
_QUANTILES = {"median_error_mrad": 0.5, "p95_error_mrad": 0.95}


def _exact(label: str, cur, base, out: list[str]) -> None:
    if cur != base:
        out.append(f"{label}: {_show(base)} -> {_show(cur)} (must match exactly)")


def _show(v) -> str:
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {v[k]}" for k in sorted(v)) + "}" if v else "{}"
    if isinstance(v, float):
        return f"{v:.4f}"
    return "missing" if v is None else str(v)


def _errors(label: str, cur: Mapping, base: Mapping, tol: Tolerances, out: list[str]) -> None:
    """Compare the error statistics of one heliostat/model/split."""
    for stat in _STATS:
        b, c = base.get(stat), cur.get(stat)
        if b is None:
            continue
        if c is None or (isinstance(c, float) and math.isnan(c)):
            out.append(f"{label}: {stat} {b:.4f} -> missing")
            continue
        allowed = tol.allowed(stat, b, base.get("n"))
        if c - b > allowed + 1e-12:
            rel = f", {100 * (c - b) / b:+.1f} %" if b else ""
            out.append(f"{label}: {stat} {b:.4f} -> {c:.4f} ({c - b:+.4f} mrad{rel}; "
                       f"allowed +{allowed:.4f})")


def _splits(label: str, cur: Mapping, base: Mapping, tol: Tolerances, out: list[str]) -> None:
    for split, bs in sorted(base.items()):
        cs = cur.get(split)
        if cs is None:
            out.append(f"{label} / {split}: split missing (baseline n = {bs.get('n')})")
            continue
        _exact(f"{label} / {split}: n", cs.get("n"), bs.get("n"), out)
        if split in tol.splits:
            _errors(f"{label} / {split}", cs, bs, tol, out)


def compare_metrics(current: Mapping, baseline: Mapping,
                    tolerances: Tolerances | Mapping | None = None) -> list[str]:
    """Differences of ``current`` against ``baseline`` (two parsed metrics.json) that regress.

    Parameters
    ----------
    current, baseline : metrics.json contents (``docs/metrics_schema.json``).
    tolerances : a :class:`Tolerances`, a mapping of its fields, or ``None`` for the defaults.

    Returns
    -------
    One human-readable line per regression, in a stable order; empty when within tolerance.
    """
    if tolerances is None:
        tol = DEFAULT_TOLERANCES
    elif isinstance(tolerances, Tolerances):
        tol = tolerances
    else:
        tol = Tolerances(**{**asdict(DEFAULT_TOLERANCES), **dict(tolerances)})
    out: list[str] = []
    cd, bd = current.get("data", {}), baseline.get("data", {})
    for key in ("n_heliostats", "n_measurements", "n_rejected", "rejected_by_reason"):
        if key in bd:
            _exact(f"data: {key}", cd.get(key), bd[key], out)
    ch, bh = current.get("heliostats", {}), baseline.get("heliostats", {})
    for hid in sorted(set(ch) - set(bh)):
        out.append(f"{hid}: heliostat not in the baseline (new heliostat: regenerate the baseline)")
    for hid in sorted(bh):
        b = bh[hid]
        c = ch.get(hid)
        if c is None:
            out.append(f"{hid}: heliostat missing (baseline has {b.get('n_measurements')} "
                       "measurements)")
            continue
        _exact(f"{hid}: n_measurements", c.get("n_measurements"), b.get("n_measurements"), out)
        _exact(f"{hid}: split_counts", c.get("split_counts"), b.get("split_counts"), out)
        cm, bm = c.get("models", {}), b.get("models", {})
        for model in sorted(bm):
            if model not in cm:
                out.append(f"{hid} / {model}: model missing")
                continue
            _splits(f"{hid} / {model}", cm[model].get("splits", {}), bm[model].get("splits", {}),
                    tol, out)
        bsel = (b.get("selection") or {}).get("model")
        csel = (c.get("selection") or {}).get("model")
        if bsel and bsel in bm:
            if not csel or csel not in cm:
                out.append(f"{hid}: no selected model (baseline selected {bsel})")
            else:
                label = f"{hid} / selected ({bsel})" if bsel == csel else \
                    f"{hid} / selected ({bsel} -> {csel})"
                cs, bs = cm[csel].get("splits", {}), bm[bsel].get("splits", {})
                for split in tol.splits:
                    if split in bs:
                        _errors(f"{label} / {split}", cs.get(split, {}), bs[split], tol, out)
    return out


def load_metrics(path: str | Path) -> dict:
    """Parse a metrics.json; :class:`ValueError` with a one-line message when it cannot be read."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"{path} does not exist (run `heliocal report` first)") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path} is not a readable metrics.json ({exc})") from None


def format_report(diffs: list[str], current: str, baseline: str) -> str:
    """The text printed for a failed comparison."""
    lines = [f"accuracy regression: {current} against baseline {baseline} "
             f"({len(diffs)} difference{'s' if len(diffs) != 1 else ''}):"]
    lines += [f"  - {d}" for d in diffs]
    lines.append(f"tolerances: mean error may grow by max({DEFAULT_TOLERANCES.mean_rel:.0%}, "
                 f"{DEFAULT_TOLERANCES.mean_abs_mrad} mrad), median and p95 by "
                 f"max({DEFAULT_TOLERANCES.quantile_rel:.0%}, "
                 f"{DEFAULT_TOLERANCES.quantile_abs_mrad} mrad), widened by sqrt("
                 f"{DEFAULT_TOLERANCES.tail_rows:g} / k) where k < {DEFAULT_TOLERANCES.tail_rows:g} "
                 "rows lie beyond the quantile, on "
                 f"{' and '.join(DEFAULT_TOLERANCES.splits)}; counts must match exactly. If the "
                 "change is intended, regenerate the baseline (docs/report.md).")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m heliocal.pipeline.report.regression",
        description="Compare a run's metrics.json with a baseline; exit 1 on an accuracy "
                    "regression.")
    parser.add_argument("current", help="metrics.json of the run to check")
    parser.add_argument("baseline", help="the committed baseline metrics.json")
    args = parser.parse_args(argv)
    try:
        cur, base = load_metrics(args.current), load_metrics(args.baseline)
    except ValueError as exc:
        print(f"Error: {exc}", file=sys.stderr)
        return 2
    diffs = compare_metrics(cur, base)
    if diffs:
        print(format_report(diffs, args.current, args.baseline), file=sys.stderr)
        return 1
    n_models = sum(len(h.get("models", {})) for h in base.get("heliostats", {}).values())
    print(f"{args.current}: within tolerance of {args.baseline} "
          f"({len(base.get('heliostats', {}))} heliostats, {n_models} heliostat-models)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
