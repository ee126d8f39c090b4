"""What ``split-knn``, ``fit-coarse`` and ``report`` need to keep their previous run on unchanged
inputs, without importing pandas, torch or scikit-learn: each stage's options as it records
them, the state the report depends on, and the summary of a kept run. The stages use these
themselves, and the command line uses them to answer an unchanged ``--incremental`` rerun before
it loads anything else (``cli/rerun.py``); the decision is
:func:`heliocal.pipeline.artifacts.unchanged.carry_over_unchanged` either way.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from ..artifacts.revision import git_revision
from ..artifacts.unchanged import keep_if_unchanged, state_digest, workdir_state
from ..errors import check_choice, check_int
from ..report.floor import MeasurementFloor, find_measurement_floor
from ..vocabulary import ReportFigures, SplitMethod, SplitMetric

__all__ = ["MIN_TRAIN", "required_measurements", "requirement_text", "split_options",
           "split_kept_summary", "coarse_options", "coarse_kept_summary", "report_options",
           "report_state", "report_kept_summary", "keep_split", "keep_coarse", "keep_report"]

#: Fewest training rows a heliostat must keep: a training row's distance to the nearest *other*
#: training row is defined only when there are two of them.
MIN_TRAIN = 2

_SPLIT = "split_knn"


# ------------------------------------------------------------------------------------------------
# split-knn
# ------------------------------------------------------------------------------------------------
def required_measurements(k: int = 3, n_test: int = 30, n_val: int = 20,
                          n_train: int | None = None) -> int:
    """Fewest measurements a heliostat needs for a split with these sizes [1]."""
    return max(n_test + n_val + (MIN_TRAIN if n_train is None else n_train), k + 1)


def requirement_text(k: int, n_test: int, n_val: int, n_train: int | None) -> str:
    """:func:`required_measurements` with what it is made of, for messages."""
    need = required_measurements(k, n_test, n_val, n_train)
    train = MIN_TRAIN if n_train is None else n_train
    if n_test + n_val + train >= k + 1:
        return f"{need} ({n_test} test + {n_val} validation + {train} training)"
    return f"{need} (k={k} neighbours plus the measurement itself)"


def split_options(method="knn", k=3, n_test=30, n_val=20, n_train=None, metric="euclidean",
                  seed=0) -> dict:
    """``split-knn``'s options, checked, as its manifest records them (ParameterError naming
    the first one out of range)."""
    method = check_choice(method, "method", _SPLIT, SplitMethod.values())
    k = check_int(k, "k", _SPLIT, 1, 3)
    n_test = check_int(n_test, "n_test", _SPLIT, 0)
    n_val = check_int(n_val, "n_val", _SPLIT, 0)
    if n_train is not None:
        n_train = check_int(n_train, "n_train", _SPLIT, MIN_TRAIN)
    metric = check_choice(metric, "metric", _SPLIT, SplitMetric.values())
    seed = check_int(seed, "seed", _SPLIT, 0)
    return {"method": method, "k": k, "n_test": n_test, "n_val": n_val, "n_train": n_train,
            "metric": metric, "seed": seed}


def split_kept_summary(workdir: str | Path, options: dict) -> dict:
    """The summary of a ``split-knn`` run that kept the previous one."""
    sizes = [options[key] for key in ("k", "n_test", "n_val", "n_train")]
    return {"artifact": str(Path(workdir) / "split.parquet"), **options,
            "required_measurements": required_measurements(*sizes),
            "requirement": requirement_text(*sizes),
            "heliostats": [], "skipped": [], "incremental": {"unchanged": True}}


def keep_split(workdir: str | Path, *, command: str | None = None, **kwargs) -> dict | None:
    """``split-knn --incremental`` when its previous run can be kept: the kept run's summary;
    ``None`` (nothing done) when it cannot."""
    options = split_options(**kwargs)
    if keep_if_unchanged(workdir, "split-knn", options, command=command) is None:
        return None
    return split_kept_summary(workdir, options)


# ------------------------------------------------------------------------------------------------
# fit-coarse
# ------------------------------------------------------------------------------------------------
def coarse_options(*, preset: str, loss: str, f_scale_mrad: float, robust_start: str,
                   solver: str, regime_steps: str, rolling_origins: int, prior: str,
                   prior_from: str | Path | None = None,
                   heliostats: Sequence[str] | None = None) -> dict:
    """``fit-coarse``'s options as its manifest records them (checked by the stage)."""
    return {"preset": preset, "loss": loss, "f_scale_mrad": f_scale_mrad,
            "robust_start": robust_start, "solver": solver, "regime_steps": regime_steps,
            "rolling_origins": rolling_origins, "prior": prior,
            "prior_from": None if prior_from is None else str(prior_from),
            "heliostats": list(heliostats) if heliostats else None}


def coarse_kept_summary(workdir: str | Path, preset: str, loss: str) -> dict:
    """The summary of a ``fit-coarse`` run that kept the previous one."""
    return {"workdir": str(workdir), "preset": preset, "loss": loss, "heliostats": [],
            "regimes": None, "field_prior": None, "incremental": {"unchanged": True}}


def keep_coarse(workdir: str | Path, *, command: str | None = None, **kwargs) -> dict | None:
    """``fit-coarse --incremental`` (every heliostat, :func:`coarse_options`' keywords) when its
    previous run can be kept: the kept run's summary; ``None`` when it cannot."""
    options = coarse_options(**kwargs)
    if options["heliostats"] or keep_if_unchanged(workdir, "fit-coarse", options,
                                                  command=command) is None:
        return None
    return coarse_kept_summary(workdir, options["preset"], options["loss"])


# ------------------------------------------------------------------------------------------------
# report
# ------------------------------------------------------------------------------------------------
def report_options(workdir: Path, out: Path, alert_mrad: float, floor_mrad: float | None,
                   figures: str, figures_for: Sequence[str]) -> dict:
    """``report``'s options as its manifest records them; the folders as given, since the pages
    show them."""
    return {"workdir": str(workdir), "out": str(out), "alert_mrad": float(alert_mrad),
            "floor_mrad": None if floor_mrad is None else float(floor_mrad),
            "figures": str(figures), "figures_for": [str(h) for h in figures_for]}


def report_state(workdir: Path, floor: MeasurementFloor) -> str:
    """The digest of what a report depends on besides its options and code: every committed run
    of the work directory and what else is in it (:func:`workdir_state`; the report reads every
    artifact there is), the measurement floor, the git revision its pages print, and the
    matplotlib version that draws its figures."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        matplotlib = version("matplotlib")
    except PackageNotFoundError:  # pragma: no cover - a dependency of heliocal
        matplotlib = None
    return state_digest({"workdir": workdir_state(workdir, skip=("report",)),
                         "floor": [floor.value_mrad, floor.source, floor.problems],
                         "git": git_revision(), "matplotlib": matplotlib})


def report_kept_summary(workdir: Path, out: Path, files: Sequence[str]) -> dict:
    """The summary of a ``report`` run that kept the previous report, whose files (relative to
    ``out``) are ``files``: its figures and pages are all kept."""
    figures = [str(out / rel) for rel in sorted(files) if rel.startswith("figures/")]
    return {"workdir": str(workdir), "report": str(out / "index.html"),
            "markdown": str(out / "report.md"), "metrics": str(out / "metrics.json"),
            "details": str(out / "details.html"), "field": str(out / "field.html"),
            "field_prior": str(out / "field_prior.html") if "field_prior.html" in files else None,
            "figures": figures, "notes": [],
            "heliostat_pages": [str(out / rel) for rel in sorted(files)
                                if rel.startswith("heliostats/")],
            "heliostats": [], "field_summary": {}, "figures_drawn": 0,
            "figures_kept": len(figures), "incremental": {"unchanged": True}}


def keep_report(workdir: str | Path, *, alert_mrad: float, floor_mrad: float | None,
                figures: str, figures_for: Sequence[str], out_dir: str | Path | None = None,
                command: str | None = None) -> dict | None:
    """``report --incremental`` when the previous report can be kept: the kept run's summary;
    ``None`` when it cannot, or when the measurement floor has a problem to warn about (the
    stage's run says it)."""
    workdir = Path(workdir)
    out = Path(out_dir) if out_dir is not None else workdir / "report"
    if figures not in ReportFigures.values() or find_measurement_floor(workdir,
                                                                      floor_mrad).problems:
        return None
    options = report_options(workdir, out, alert_mrad, floor_mrad, figures, figures_for)
    state = lambda: report_state(workdir, find_measurement_floor(workdir, floor_mrad))  # noqa: E731
    kept = keep_if_unchanged(out, "report", options, workdir=workdir, command=command,
                             state=state)
    return None if kept is None else report_kept_summary(workdir, out, list(kept.files))
