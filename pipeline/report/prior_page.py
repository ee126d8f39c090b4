"""The report's page of the field prior (``field_prior.html``, issue 34): written when
``fit-coarse`` fitted under a field prior (``--prior field``, ``field+spatial`` or
``--prior-from``; field_prior.parquet has rows).

Per group of heliostats (kinematic type, actuator type, geometry source) it shows the prior of
one preset, the one most of the group's heliostats select: each parameter's mean, scale and
number of heliostats (field_prior.parquet, the other presets folded below), the prior against
the fitted values of the group's heliostats (:mod:`.prior_figures`), how much each
heliostat's fit leans on it (coarse_params.parquet ``prior_shrinkage``, a heatmap and a table),
and, when the sweep ran a training-size study, the shown preset's test error against training
rows with and without the prior (sweep.parquet's ``<preset>`` and ``<preset>+no-field-prior``,
:mod:`heliocal.pipeline.stages.study_prior`).
Numbers are shown in display units (mrad, mm, per mille of the nominal increment); each cell
keeps the artifact's value in ``data-v``. Every text from the data is escaped.
"""

from __future__ import annotations

import html
import math
import urllib.parse
from dataclasses import dataclass
from typing import Sequence

import pandas as pd

from .field import heliostat_page_name
from .metrics import WITHOUT_FIELD_PRIOR, column_of
from .pages import fmt, inline_html as inline, page_head
from .prior_figures import DISPLAY_UNITS
from .render import FigureTask

__all__ = ["DISPLAY_UNITS", "PRIOR_PAGE", "PriorGroup", "display_value", "prior_groups",
           "prior_page_html", "prior_page_tasks", "study_curves", "training_size_note"]

e = html.escape

#: The page's file name.
PRIOR_PAGE = "field_prior.html"

_GROUP_COLUMNS = ("kinematic_type", "actuator_type", "geometry_source")


def display_value(value: float, unit: str) -> tuple[float, str]:
    """A field_prior.parquet value [``unit``] in the page's display unit: (value, unit)."""
    factor, shown = DISPLAY_UNITS.get(str(unit), (1.0, str(unit)))
    return float(value) * factor, shown


@dataclass
class PriorGroup:
    """What the page shows of one group: its key, the preset shown, field_prior.parquet's rows
    of the group (all presets) and the group's heliostats' fits of that preset (coarse_params
    rows, one per heliostat and parameter, with ``deviation``: fitted minus nominal in
    field_prior.parquet's units, and ``selected_model``)."""

    key: tuple[str, str, str]
    preset: str
    table: pd.DataFrame
    fits: pd.DataFrame

    @property
    def name(self) -> str:
        return " / ".join(self.key)

    @property
    def slug(self) -> str:
        return "_".join("".join(c if c.isalnum() else "-" for c in part) for part in self.key)

    def prior_rows(self) -> pd.DataFrame:
        """The shown preset's rows with a field prior (a scale), in parameter order."""
        t = self.table[(self.table["preset"] == self.preset) & self.table["scale"].notna()]
        return t.sort_values("parameter_index")


def _shown_preset(table: pd.DataFrame, selected: pd.Series) -> str:
    """The preset whose prior a group's page shows: the one most of its heliostats select (a
    regime-aware candidate or the field-prior geometry counts for its base preset), among those
    with a field prior; else the one with the most parameters with a prior."""
    with_prior = table[table["scale"].notna()].groupby("preset").size()
    if with_prior.empty:
        return str(table["preset"].iloc[0])
    votes = selected.astype(str).str.split("+").str[0].value_counts()
    votes = votes[votes.index.isin(with_prior.index)]
    if len(votes):
        return str(votes.sort_index().idxmax())
    return str(with_prior.sort_index().idxmax())


def prior_groups(field_prior: pd.DataFrame | None, coarse_params: pd.DataFrame | None,
                 group_of: dict[str, tuple[str, str, str]]) -> list[PriorGroup]:
    """The groups of a run with a field prior (none without one: the page is not written).
    ``coarse_params`` with a ``deviation`` column (fitted minus nominal in field_prior.parquet's
    units; the stage adds it, :func:`~heliocal.pipeline.stages.coarse_prior.with_deviations`);
    ``group_of``: heliostat -> its group (kinematic type, actuator type, geometry source)."""
    if field_prior is None or field_prior.empty or coarse_params is None:
        return []
    cp = coarse_params.assign(heliostat_id=coarse_params["heliostat_id"].astype(str))
    chosen = cp[cp["selected"].astype(bool)].drop_duplicates("heliostat_id")
    selected = dict(zip(chosen["heliostat_id"], chosen["preset"].astype(str)))
    groups = []
    for key, table in field_prior.groupby(list(_GROUP_COLUMNS), sort=True):
        members = [h for h, k in group_of.items() if tuple(k) == tuple(key)]
        preset = _shown_preset(table, pd.Series([selected[h] for h in members if h in selected],
                                                dtype=str))
        fits = cp[cp["heliostat_id"].isin(members) & (cp["preset"] == preset)].copy()
        fits = fits.sort_values(["heliostat_id", "parameter_index"])
        fits["selected_model"] = fits["heliostat_id"].map(selected).fillna("")
        groups.append(PriorGroup(tuple(str(k) for k in key), preset, table.copy(), fits))
    return groups


def study_curves(g: PriorGroup, sweep: pd.DataFrame | None) -> pd.DataFrame:
    """The training-size study's rows of the group's shown preset, with (``prior`` ``field``:
    model ``<preset>``) and without the prior (``none``: ``<preset>+no-field-prior``), of the
    study heliostats that have both (columns ``heliostat_id``, ``prior``, ``n_train``,
    ``test_error_mrad``, ``full``: the heliostat's full training size); empty without."""
    columns = ["heliostat_id", "prior", "n_train", "test_error_mrad", "full"]
    test = column_of(sweep, "test")
    if test is None or not {"heliostat_id", "model", "n_train"} <= set(sweep.columns):
        return pd.DataFrame(columns=columns)
    sweep = sweep.assign(test_error_mrad=sweep[test])
    members = set(g.fits["heliostat_id"].astype(str))
    s = sweep[sweep["heliostat_id"].astype(str).isin(members)]
    without = s[s["model"].astype(str) == g.preset + WITHOUT_FIELD_PRIOR]
    s = s[s["heliostat_id"].isin(set(without["heliostat_id"]))]
    rows = pd.concat([s[s["model"].astype(str) == g.preset].assign(prior="field"),
                      without.assign(prior="none")], ignore_index=True)
    rows = rows.assign(heliostat_id=rows["heliostat_id"].astype(str),
                       n_train=rows["n_train"].astype(int))
    rows["full"] = rows.groupby("heliostat_id")["n_train"].transform("max")
    return rows[columns].sort_values(["prior", "heliostat_id", "n_train"]).reset_index(drop=True)


def prior_page_tasks(groups: Sequence[PriorGroup],
                     sweep: pd.DataFrame | None = None) -> list[FigureTask]:
    """Per group the prior against the fitted values, the shrinkage heatmap and, where the
    sweep's study fitted the group's preset with and without the prior, its training-size
    curves (drawn by :func:`.prior_figures.draw_prior_figure`; args are small frames, so the
    figures' digests change only when the numbers do)."""
    tasks = []
    for g in groups:
        curves = study_curves(g, sweep)
        if len(curves):
            n = curves["heliostat_id"].nunique()
            tasks.append(FigureTask(
                "prior_training_size", f"field_prior_sizes_{g.slug}.png",
                f"{g.name}, {g.preset}: mean test error against training rows of the sweep's "
                f"training-size study ({n} heliostat{'s' if n != 1 else ''}), fitted as "
                "fit-coarse fits them under the field prior it gave each heliostat (blue) and "
                "without it (red; the default weak prior around the nominal geometry). Thick "
                "lines: the median over the heliostats with that many rows (thin: each "
                "heliostat, up to 8); diamonds: each heliostat with all its training rows.",
                None, {"frame": curves, "preset": g.preset}))
        rows = g.prior_rows()
        params = rows[["parameter_index", "parameter", "unit", "mean", "scale",
                       "n_heliostats"]].reset_index(drop=True)
        fits = g.fits[g.fits["parameter_index"].isin(params["parameter_index"])]
        points = fits[["heliostat_id", "parameter_index", "deviation", "prior_shrinkage",
                       "n_train"]].reset_index(drop=True)
        tasks.append(FigureTask(
            "prior_vs_fitted", f"field_prior_{g.slug}.png",
            f"{g.name}, {g.preset}: each parameter's field prior (line: its mean; bands: one and "
            "two scales) against the fitted deviations from nominal of the group's heliostats "
            "(dots, by training rows; colour: how much the fit leans on the prior, 0 data "
            "alone, 1 prior alone). Each heliostat's own prior leaves its fold out, so it is "
            "not exactly the group's prior drawn here.", None,
            {"params": params, "points": points}))
        tasks.append(FigureTask(
            "prior_shrinkage", f"field_prior_shrinkage_{g.slug}.png",
            f"{g.name}, {g.preset}: how much each heliostat's fit of each parameter leans on "
            "the field prior (prior_shrinkage: 0 the data alone fix it, 1 the data say nothing "
            "about it), heliostats by training rows, fewest at the top.", None,
            {"points": points, "params": params[["parameter_index", "parameter"]]}))
    return tasks


def _cell(value, digits: int = 3, raw=None) -> str:
    """A numeric table cell showing ``value`` with the artifact's value ``raw`` in data-v."""
    raw = value if raw is None else raw
    v = "" if raw is None or (isinstance(raw, float) and not math.isfinite(raw)) else \
        f' data-v="{float(raw)!r}"'
    return f"<td{v}>{e(fmt(value, digits))}</td>"


def _prior_table(rows: pd.DataFrame) -> str:
    head = ["preset", "parameter", "unit", "mean", "scale", "heliostats", "spatial mean"]
    out = ['<table class="sortable prior"><thead><tr>'
           + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr></thead><tbody>"]
    for _, r in rows.iterrows():
        mean, unit = display_value(r["mean"], r["unit"])
        scale, _ = display_value(r["scale"], r["unit"])
        out.append(f'<tr data-parameter="{e(str(r["parameter"]))}" '
                   f'data-preset="{e(str(r["preset"]))}"><td>{e(str(r["preset"]))}</td>'
                   f'<td>{e(str(r["parameter"]))}</td><td>{e(unit)}</td>'
                   + _cell(mean, 3, float(r["mean"])) + _cell(scale, 3, float(r["scale"]))
                   + _cell(int(r["n_heliostats"])) + f"<td>{fmt(bool(r['spatial']))}</td></tr>")
    out.append("</tbody></table>")
    return "\n".join(out)


def _heliostat_rows(g: PriorGroup) -> pd.DataFrame:
    """Per heliostat of the group: training rows, selected model, noises and its shrinkage
    over the parameters with a field prior (median, and the largest with its parameter; a
    fit's parameters that keep the default prior have a shrinkage too, toward that prior, and
    are left out here)."""
    f = g.fits[g.fits["prior_shrinkage"].notna()
               & g.fits["parameter_index"].isin(g.prior_rows()["parameter_index"])]
    rows = []
    for hid, h in f.groupby("heliostat_id", sort=True):
        top = h.loc[h["prior_shrinkage"].idxmax()]
        rows.append({"heliostat_id": hid, "n_train": int(h["n_train"].iloc[0]),
                     "model": h["selected_model"].iloc[0],
                     "own_noise_mrad": float(h["own_noise_mrad"].iloc[0]),
                     "prior_noise_mrad": float(h["prior_noise_mrad"].iloc[0]),
                     "median": float(h["prior_shrinkage"].median()),
                     "max": float(top["prior_shrinkage"]), "max_parameter": top["parameter"]})
    return pd.DataFrame(rows)


def _heliostat_table(g: PriorGroup) -> str:
    rows = _heliostat_rows(g)
    if rows.empty:
        return '<p class="note">No heliostat of the group was fitted under the prior.</p>'
    head = ["heliostat", "selected model", "training rows", "own noise [mrad]",
            "prior weighed against [mrad]", "shrinkage: median", "largest", "largest for"]
    out = ['<table class="sortable"><thead><tr>' + "".join(f"<th>{e(h)}</th>" for h in head)
           + "</tr></thead><tbody>"]
    for _, r in rows.sort_values(["n_train", "heliostat_id"]).iterrows():
        link = "heliostats/" + urllib.parse.quote(heliostat_page_name(str(r["heliostat_id"])))
        out.append(f'<tr><td><a href="{e(link)}">{e(str(r["heliostat_id"]))}</a></td>'
                   + f'<td>{e(str(r["model"]))}</td>' + _cell(int(r["n_train"]))
                   + _cell(r["own_noise_mrad"]) + _cell(r["prior_noise_mrad"])
                   + _cell(r["median"], 2) + _cell(r["max"], 2)
                   + f'<td>{e(str(r["max_parameter"]))}</td></tr>')
    out.append("</tbody></table>")
    return "\n".join(out)


def _figure(drawn: dict, task: FigureTask) -> str:
    png, why = drawn.get(task.filename, (None, "not drawn"))
    if png is None:
        return f'<p class="note">Figure omitted ({e(str(why))}).</p>'
    src = "figures/" + urllib.parse.quote(task.filename)
    return (f'<figure id="{e(task.filename)}"><img loading="lazy" alt="{e(task.caption)}" '
            f'src="{e(src)}"><figcaption>{e(task.caption)}</figcaption></figure>')


def _how_learnt(options: dict) -> str:
    """The paragraph saying how the prior was learnt and given (docs/field_prior.md)."""
    if options.get("prior_from"):
        source = (f"The prior is another work directory's (`--prior-from {options['prior_from']}`"
                  "), learnt there from its own field, as below; this run's fits only use it.")
    else:
        source = (f"Learnt by this run (`fit-coarse --prior {options.get('prior', 'field')}`) "
                  "from the field itself: the heliostats of each group with the most rows (at "
                  "most 256) were fitted under the default weak prior on their rows that are not "
                  "test rows; a parameter's prior is the median deviation from nominal of the "
                  "fits that determine it, its scale the field's spread without the fits' own "
                  "noise.")
    return (source + " Each heliostat was then fitted by MAP under the prior estimated without "
            "its own fold (leave-one-out up to 20 heliostats, 20 folds by a hash of the ids "
            "above), so its own rows never inform its own prior, and no test row informs any. "
            "A parameter gets the field prior only where at least 8 heliostats of its group "
            "(outside the fold) determine it; elsewhere the fit keeps the default prior. The "
            "prior is weighed against the heliostat's own noise (at most the field's). How, "
            "and the definition of shrinkage: `docs/field_prior.md` in the heliocal "
            "repository.")


def _group_html(g: PriorGroup, drawn: dict, tasks: dict) -> list[str]:
    rows = g.prior_rows()
    first = (rows if len(rows) else g.table).iloc[0]
    n_fitted = g.fits.loc[g.fits["prior_noise_mrad"].notna(), "heliostat_id"].nunique()
    expected = first["expected_error_mrad"]
    line = (f"Preset shown: {g.preset} (the one most of the group's heliostats select); "
            f"{len(rows)} of its parameters have a field prior, estimated from up to "
            f"{int(rows['n_heliostats'].max()) if len(rows) else 0} heliostats; "
            f"{n_fitted} heliostat{'s were' if n_fitted != 1 else ' was'} fitted under it. "
            "The field's noise the prior is weighed against: "
            f"{fmt(float(first['noise_mrad']))} mrad.")
    if isinstance(expected, float) and math.isfinite(expected):
        line += (f" The field-prior geometry (nominal moved by the prior mean) is off by "
                 f"{fmt(expected)} mrad on the test rows of {int(first['n_evaluated'])} "
                 f"heliostats (median; nominal geometry {fmt(first['nominal_error_mrad'])} "
                 "mrad).")
    out = [f'<h2 id="{e(g.slug)}">{e(g.name)}</h2>', f"<p>{inline(line)}</p>"]
    out.append(_prior_table(rows) if len(rows) else
               '<p class="note">No parameter of this preset has a field prior.</p>')
    default = g.table[(g.table["preset"] == g.preset) & g.table["scale"].isna()]
    if len(default):
        out.append("<p>Default prior (fewer than 8 determining heliostats): "
                   + e(", ".join(default.sort_values("parameter_index")["parameter"])) + ".</p>")
    others = g.table[(g.table["preset"] != g.preset) & g.table["scale"].notna()]
    if len(others):
        out.append(f"<details><summary>The other presets' priors ({len(others)} rows)"
                   "</summary>" + _prior_table(others.sort_values(["preset", "parameter_index"]))
                   + "</details>")
    out.append(_figure(drawn, tasks[f"field_prior_{g.slug}.png"]))
    out.append("<h3>Shrinkage per heliostat</h3>")
    out.append(_figure(drawn, tasks[f"field_prior_shrinkage_{g.slug}.png"]))
    out.append(_heliostat_table(g))
    sizes = tasks.get(f"field_prior_sizes_{g.slug}.png")
    if sizes is not None:
        out.append("<h3>Training size, with and without the prior</h3>")
        out.append(_figure(drawn, sizes))
    return out


def training_size_note(has_study: bool, has_curves: bool = False) -> str:
    """What the page says of training-size curves with and without the prior (``has_curves``:
    a group's figure of them is on the page)."""
    if has_curves:
        text = ("The sweep's training-size study refits the coarse presets at each size as "
                "fit-coarse fits them, under the field prior it gave each heliostat (its "
                "leave-out fold's), and again without it (sweep.parquet model "
                "`<preset>+no-field-prior`); each group above draws the two curves of its "
                "preset. The training-size figures of field.html and the heliostat pages show "
                "the presets as fit-coarse fits them, with the prior, and the other models.")
    elif has_study:
        text = ("No heliostat of the sweep's training-size study has its group's preset "
                "fitted both with and without the field prior (the study's heliostats are in "
                "other groups, or the sweep ran before the study fitted both: run `heliocal "
                "sweep` again), so there are no curves with and without the prior here.")
    else:
        text = "This work directory has no training-size study (`heliocal sweep --study N`)."
    return text + (" `benchmarks/field_prior.py` measures the error at 3, 5, 10 and 20 training "
                   "rows with and without the prior on every heliostat "
                   "(docs/experiments/field-prior.md).")


def prior_page_html(title: str, nav: str, sort_js: str, groups: Sequence[PriorGroup],
                    tasks: Sequence[FigureTask], drawn: dict, options: dict,
                    training_size_note: str) -> str:
    """``field_prior.html``: how the prior was learnt, then per group its prior, the figure of
    the prior against the fitted values, the shrinkage heatmap and table; last the
    training-size note. ``drawn``: file name -> (png or None, why) of ``tasks``."""
    by_name = {t.filename: t for t in tasks}
    out = page_head(f"Field prior: {title}")
    out.append(nav)
    out.append("<h1>Field prior</h1>")
    out.append(f"<p>{inline(_how_learnt(options))}</p>")
    out.append("<p>Shrinkage (coarse_params.parquet <code>prior_shrinkage</code>) is how much "
               "a fitted parameter leans on its field prior: the posterior variance over the "
               "prior variance in the fit's last Gauss-Newton system, equally how far the "
               "fitted value moves when the prior's mean moves (0: the data alone fix it, 1: "
               "the data say nothing about it).</p>")
    if groups:
        out.append("<p>Groups: " + ", ".join(f'<a href="#{e(g.slug)}">{e(g.name)}</a>'
                                             for g in groups) + ".</p>")
    for g in groups:
        out += _group_html(g, drawn, by_name)
    out.append("<h2>Training size</h2>")
    out.append(f'<p class="note">{inline(training_size_note)}</p>')
    out.append(sort_js)
    out.append("</body></html>")
    return "\n".join(out) + "\n"
