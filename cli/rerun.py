"""An ``--incremental`` rerun of ``split-knn``, ``fit-coarse`` or ``report`` on unchanged inputs,
answered before the command-line framework loads.

Typer (with pydantic and rich) takes about 0.2 s to start, as long as a ``split-knn`` rerun may
take on a 200-heliostat field (5 % of its first run). So :func:`heliocal.cli.main.main` first hands
its arguments to :func:`run_if_unchanged`: when they are an ``--incremental`` run of one of these
stages, spelled with the options of :data:`COMMANDS` only, the stage's own rule decides from the
manifests whether its previous run can be kept (:mod:`heliocal.pipeline.stages.rerun`) and, if
so, this prints what the command prints for a kept run. Anything else (another command, an
option or a spelling not listed here, a value the command would refuse, ``--help``, inputs,
options or code that changed) returns ``None`` with nothing done, and the command runs as usual,
where the same rule is applied again. tests/test_unchanged_rerun.py checks that the options here
are the commands' own (names, defaults, ranges and choices).
"""

from __future__ import annotations

import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from heliocal.pipeline.vocabulary import (DEFAULT_ALERT_MRAD, DEFAULT_ROLLING_ORIGINS, CoarseLoss,
                                          CoarsePreset, CoarsePrior, CoarseSolver, ReportFigures,
                                          RobustStart, Scheduler, SplitMethod, SplitMetric)

__all__ = ["Opt", "COMMANDS", "UNCHANGED_LINE", "parse", "run_if_unchanged"]

#: What a command prints for a run that kept its previous run's files.
UNCHANGED_LINE = ("unchanged: the inputs, options and code are the previous run's; its "
                  "artifacts are kept as they are.")

_INT = re.compile(r"[+-]?[0-9]+")
_FLOAT = re.compile(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?")


@dataclass(frozen=True)
class Opt:
    """One option of a command: its spellings, the command function's parameter, the kind of its
    value (``flag``, ``int``, ``float``, ``path``, ``choice``; ``many``: a repeatable text), its
    default, choices and range (inclusive)."""

    names: tuple[str, ...]
    param: str
    kind: str
    default: object = None
    choices: tuple[str, ...] = ()
    low: float | None = None
    high: float | None = None

    def value(self, text: str):
        """The value of ``text``, or ``None`` when the command could refuse it or read it
        otherwise than this does (then the command itself runs)."""
        if self.kind == "int" and _INT.fullmatch(text):
            value = int(text)
        elif self.kind == "float" and _FLOAT.fullmatch(text):
            value = float(text)
        elif self.kind == "choice" and text in self.choices:
            return text
        elif self.kind == "path" and text and "\0" not in text:
            return Path(text)
        elif self.kind == "many" and text:
            return text
        else:
            return None
        if (self.low is not None and value < self.low) or (self.high is not None
                                                          and value > self.high):
            return None
        return value


def _flags() -> list[Opt]:
    return [Opt(("--workdir", "-w"), "workdir", "path", Path("runs/default")),
            Opt(("--incremental",), "incremental", "flag", False),
            Opt(("--json",), "json_", "flag", False),
            Opt(("--quiet", "-q"), "quiet", "flag", False)]


#: The options each command's early answer knows (the others make the command run as usual).
COMMANDS: dict[str, list[Opt]] = {
    "split-knn": _flags() + [
        Opt(("--method",), "method", "choice", "knn", SplitMethod.values()),
        Opt(("--k",), "k", "int", 3, low=1, high=3),
        Opt(("--n-test",), "n_test", "int", 30, low=0),
        Opt(("--n-val",), "n_val", "int", 20, low=0),
        Opt(("--n-train",), "n_train", "int", None, low=2),
        Opt(("--metric",), "metric", "choice", "euclidean", SplitMetric.values()),
        Opt(("--seed",), "seed", "int", 0)],
    "fit-coarse": _flags() + [
        Opt(("--preset",), "preset", "choice", "auto", CoarsePreset.values()),
        Opt(("--loss",), "loss", "choice", "soft_l1", CoarseLoss.values()),
        Opt(("--f-scale",), "f_scale", "float", 1.0),
        Opt(("--robust-start",), "robust_start", "choice", "auto", RobustStart.values()),
        Opt(("--solver",), "solver", "choice", "batched", CoarseSolver.values()),
        Opt(("--prior",), "prior", "choice", None, CoarsePrior.values()),
        Opt(("--rolling-origins",), "rolling_origins", "int", DEFAULT_ROLLING_ORIGINS, low=0),
        # the workers and scheduler do not change the results; a kept run starts none
        Opt(("--workers",), "workers", "int", None, low=1),
        Opt(("--scheduler",), "scheduler", "choice", "local", (Scheduler.local.value,))],
    "report": _flags() + [
        Opt(("--workers",), "workers", "int", None, low=1),
        Opt(("--alert-mrad",), "alert_mrad", "float", DEFAULT_ALERT_MRAD, low=0.0),
        Opt(("--floor-mrad",), "floor_mrad", "float", None, low=0.0),
        Opt(("--figures",), "figures", "choice", "auto", ReportFigures.values()),
        Opt(("--figures-for",), "figures_for", "many", None)],
}


def parse(argv: list[str]) -> tuple[str, dict] | None:
    """(command, parameter -> value, defaults filled in) of ``argv`` when every word of it is
    one of :data:`COMMANDS`' spellings, each option at most once (``--figures-for`` repeats);
    else ``None``."""
    if not argv or argv[0] not in COMMANDS:
        return None
    opts = COMMANDS[argv[0]]
    by_name = {name: opt for opt in opts for name in opt.names}
    values: dict = {}
    words = iter(argv[1:])
    for word in words:
        name, eq, text = word.partition("=") if word.startswith("--") else (word, "", "")
        opt = by_name.get(name)
        if opt is None or (opt.param in values and opt.kind != "many"):
            return None
        if opt.kind == "flag":
            if eq:
                return None
            values[opt.param] = True
            continue
        if not eq:
            text = next(words, None)
            if text is None or text.startswith("-"):
                return None
        value = opt.value(text)
        if value is None:
            return None
        values[opt.param] = values.get(opt.param, []) + [value] if opt.kind == "many" else value
    return argv[0], {opt.param: values.get(opt.param, opt.default) for opt in opts}


def _keep_split(v: dict, command: str) -> dict | None:
    from heliocal.pipeline.stages.rerun import keep_split

    return keep_split(v["workdir"], method=v["method"], k=v["k"], n_test=v["n_test"],
                      n_val=v["n_val"], n_train=v["n_train"], metric=v["metric"],
                      seed=v["seed"], command=command)


def _keep_coarse(v: dict, command: str) -> dict | None:
    from heliocal.pipeline.stages.rerun import keep_coarse

    # as the command: regime steps "candidates"; the prior "none" unless asked for
    return keep_coarse(v["workdir"], preset=v["preset"], loss=v["loss"],
                       f_scale_mrad=v["f_scale"], robust_start=v["robust_start"],
                       solver=v["solver"], regime_steps="candidates",
                       rolling_origins=v["rolling_origins"], prior=v["prior"] or "none",
                       command=command)


def _keep_report(v: dict, command: str) -> dict | None:
    from heliocal.pipeline.stages.rerun import keep_report

    named = [h.strip() for item in v["figures_for"] or () for h in item.split(",") if h.strip()]
    return keep_report(v["workdir"], alert_mrad=v["alert_mrad"], floor_mrad=v["floor_mrad"],
                       figures=v["figures"], figures_for=named, command=command)


_KEEP: dict[str, Callable[[dict, str], dict | None]] = {
    "split-knn": _keep_split, "fit-coarse": _keep_coarse, "report": _keep_report}


def run_if_unchanged(argv: list[str]) -> int | None:
    """Answer ``heliocal ARGV`` here when it is an ``--incremental`` run of a stage of
    :data:`COMMANDS` whose previous run can be kept: print the command's output for it and
    return the exit code (0). ``None`` when the command is to run as usual: nothing was done
    (an error on the way, such as a busy work directory, is the command's to report)."""
    from heliocal.pipeline.errors import HeliocalError

    parsed = parse(argv)
    if parsed is None or not parsed[1]["incremental"]:
        return None
    stage, values = parsed
    try:
        summary = _KEEP[stage](values, "heliocal " + " ".join(argv))
    except (HeliocalError, OSError):
        return None
    if summary is None:
        return None
    if values["json_"]:
        sys.stdout.write(json.dumps(summary, indent=2, sort_keys=False, default=str) + "\n")
    else:
        print(UNCHANGED_LINE)
    return 0
