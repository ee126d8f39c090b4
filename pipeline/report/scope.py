"""Whose own figures the report draws (``heliocal report --figures``, ``--figures-for``).

A heliostat's own figures (sky map, error over time, regimes, weight decay; training size for the
heliostats of the sweep's study; the GP correction) cost about 0.1-0.2 s of CPU each to draw, so
four per heliostat of a 2,000-heliostat field are most of the report's time and half a gigabyte of
PNG files that nobody opens: a plant engineer opens the heliostats the overview points at. So:

* ``all``: every heliostat's figures;
* ``attention``: the figures of the heliostats that need attention: on alert, the ones the
  overview lists first (:func:`.field.worst`), the heliostats of the sweep's training-size study
  (their figures are the study's); every other heliostat keeps its page with its numbers, tables
  and next-day curve, and a note saying how to draw its figures;
* ``auto`` (default): ``all`` up to :data:`EVERY_HELIOSTAT_UP_TO` heliostats, else ``attention``.

``figures_for`` adds named heliostats to any of them (``--figures-for H1,H2``); with
``--incremental`` the figures already drawn are kept, so adding one heliostat draws only its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import pandas as pd

from ..errors import InputError, check_choice
from ..vocabulary import ReportFigures

__all__ = ["EVERY_HELIOSTAT_UP_TO", "FigureScope", "figure_scope", "study_heliostats"]

#: ``--figures auto`` draws every heliostat's figures up to this many heliostats in the field
#: (400 figures; the sample and a research field's few dozen keep all of theirs).
EVERY_HELIOSTAT_UP_TO = 100


@dataclass(frozen=True)
class FigureScope:
    """The heliostats whose own figures the report draws, and why the others have none."""

    mode: str                       # "all" or "attention" ("auto" resolved)
    heliostats: frozenset[str]      # whose figures are drawn
    n_field: int                    # heliostats in the field
    workdir: str = "DIR"            # named in the command of a page's note

    @property
    def every(self) -> bool:
        """True when every heliostat of the field has its figures."""
        return len(self.heliostats) == self.n_field

    def covers(self, heliostat: str) -> bool:
        return heliostat in self.heliostats

    def field_note(self) -> str | None:
        """The note before the figures of details.html and report.md (None: every heliostat's
        figures are drawn)."""
        if self.every:
            return None
        return (f"Figures of {len(self.heliostats)} of the {self.n_field} heliostats: "
                f"{self._why()}. Every heliostat keeps its page with its numbers and tables; "
                f"`heliocal report --workdir {self.workdir} --incremental --figures-for ID` "
                "adds one heliostat's figures, `--figures all` draws every heliostat's.")

    def page_note(self, heliostat: str) -> str:
        """The note on the page of a heliostat whose figures are not drawn."""
        return (f"No figures drawn for {heliostat}: {self._why()}. Draw its figures with "
                f"`heliocal report --workdir {self.workdir} --incremental --figures-for "
                f"{heliostat}` (the figures already drawn are kept).")

    def _why(self) -> str:
        how = (f"at field scale (more than {EVERY_HELIOSTAT_UP_TO} heliostats) `--figures auto` "
               "draws" if self.mode == "auto" else "`--figures attention` draws")
        return (how + " the figures of the heliostats that need attention: on alert, listed "
                "first on the overview, in the sweep's training-size study, or named with "
                "`--figures-for`")


def study_heliostats(sweep: pd.DataFrame | None) -> set[str]:
    """The heliostats of the sweep's training-size study (two or more training sizes)."""
    if sweep is None or not {"heliostat_id", "n_train"} <= set(sweep.columns):
        return set()
    sizes = sweep.groupby(sweep["heliostat_id"].astype(str))["n_train"].nunique()
    return set(sizes.index[sizes >= 2])


def figure_scope(table: pd.DataFrame, mode: str = "auto", figures_for: Iterable[str] = (),
                 first: Iterable[str] = (), study: Iterable[str] = (),
                 workdir: str = "DIR") -> FigureScope:
    """Whose figures the report draws (see the module's docstring).

    Parameters
    ----------
    table : the field table (:func:`.field.field_table`: ``heliostat_id``, ``alerts``,
        ``test_error_mrad``).
    mode : ``auto``, ``all`` or ``attention``.
    figures_for : heliostats whose figures are drawn in any mode; each must be in ``table``.
    first : the heliostats the overview lists first (:func:`.field.worst`).
    study : the heliostats of the sweep's training-size study (:func:`study_heliostats`).
    workdir : the work directory, named in the notes' commands.
    """
    mode = str(check_choice(str(mode), "figures", "report", ReportFigures.values()))
    ids = table["heliostat_id"].astype(str).tolist()
    named = [str(h) for h in figures_for]
    unknown = sorted(set(named) - set(ids))
    if unknown:
        shown = ", ".join(repr(h) for h in unknown[:5]) + (" ..." if len(unknown) > 5 else "")
        raise InputError(f"--figures-for names {shown}, not a heliostat of {workdir} (the "
                         "heliostats are listed on the report's heliostats.html)")
    if mode == "all" or (mode == "auto" and len(ids) <= EVERY_HELIOSTAT_UP_TO):
        return FigureScope("all" if mode == "all" else "auto", frozenset(ids), len(ids),
                           workdir)
    alerted = table.loc[table["alerts"].map(len) > 0, "heliostat_id"].astype(str)
    chosen = (set(alerted) | {str(h) for h in first}
              | (set(study) & set(ids)) | set(named))
    return FigureScope(mode, frozenset(chosen), len(ids), workdir)
