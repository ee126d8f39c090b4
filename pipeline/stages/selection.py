"""The sweep's production selection of one heliostat (issue 35): its fine candidates at their
fades, the rule of :mod:`heliocal.pipeline.models.selection`, the forward-in-time check of
every fine choice (issue 33) and what the sweep writes for the choice.

A :class:`CandidatePool` collects one heliostat's candidates as the sweep trains them:

- each hybrid ensemble (band set, weight decay, seed) at the sun fade length of
  :data:`heliocal.pipeline.models.fade.FADE_LENGTHS_DEG` its weighted validation error likes
  best (:func:`heliocal.pipeline.models.selection.choose_fade`) and the time fade
  :data:`heliocal.pipeline.models.fade.NETWORK_TIME_FADE_DAYS` (its inputs include the date);
- the Gaussian-process correction (``gp``) of the structure with the highest marginal
  likelihood and, when that structure has time, the ``sun`` structure too (a static candidate:
  the fallback of the forward check, and the simpler model of the one-standard-error rule);
- with ``sweep --select-pretrained`` the pre-trained network (no fade: it predicts steps).

:meth:`CandidatePool.choose` applies the rule. Every fine choice must not be worse forward in
time than the static choice (issue 33, item 3): on the time split's validation rows, the same
model trained on the time split's training rows against fit-coarse's time-split fit. A plant
aims forward in time, and a model without date inputs can fail there too: a GP of the sun
alone fitted to a misfit of its training period learns it as a sky pattern that does not last
(a simulated heliostat: 3.57 mrad forward against its coarse model's 0.35). A GP, with time or
without, is checked here (its time-split fit costs tens of milliseconds); a network's (a
hybrid's, the pre-trained network's) time-split training is the sweep's forward pass
(:func:`heliocal.pipeline.stages.forward.add_sweep_time_split`), after which
:func:`apply_forward_checks` falls back to the static choice where the network is worse. The
static choice is the rule among the GPs without time input and the coarse model, each such GP
itself checked forward.

A GP refused forward gives way to the rule's next choice among the other candidates, networks
included: on a heliostat whose sky correction does not last, a hybrid may still (its forward
pass then runs without ``--time-split`` too, so that it is checked like the GP it replaces).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import torch

from ..models.coarse import metrics_frame
from ..models.fade import FADE_LENGTHS_DEG, NETWORK_TIME_FADE_DAYS, TIME_FADE_DAYS, Fade
from ..models.gp import GPConfig
from ..models.gp_heliostat import HeliostatGP, fit_heliostat_gps, with_correction_map
from ..models.network import layers_to_state
from ..models.regime_fit import MIN_REGIME_ROWS
from ..models.selection import (Candidate, Judgement, SelectionRule, choose_fade,
                                row_validation_weights, select)
from ..models.training import faded_errors_mrad, predict_ensembles, predictions_frame
from ..physics.metrics import mean_or_nan

__all__ = [
    "FORWARD_TOLERANCE",
    "METRICS",
    "selected_frame",
    "HeliostatChoice",
    "CandidatePool",
    "apply_forward_checks",
    "gp_time_errors",
    "latest_regime_labels",
    "study_gps",
    "time_labels",
]

#: "Not worse forward in time" leaves this much (relative) to the rows' rounding: a GP whose time
#: component the fade has switched off forward in time differs from the coarse model there in the
#: seventh digit (the Jülich log's BD41: 7.756803 against 7.756802 mrad), which is a tie.
FORWARD_TOLERANCE = 0.01

#: The metric columns of selected_predictions.parquet.
METRICS = ("error_mrad", "beam_error_mrad", "spot_offset_horizontal_m", "spot_offset_vertical_m",
           "spot_offset_m")


def selected_frame(h, metrics: pd.DataFrame) -> pd.DataFrame:
    """selected_predictions rows of one heliostat from a frame of the metric columns."""
    out = metrics[list(METRICS)].reset_index(drop=True).copy()
    out["measurement_id"] = h.rows["measurement_id"].astype(str).to_numpy()
    out["heliostat_id"], out["split"] = h.hid, h.labels
    out["model"], out["selected"] = "selected", True
    return out


def _length_rank(length: float) -> int:
    """Shorter fades are simpler (closer to the coarse model): 0 for the shortest."""
    return sorted(FADE_LENGTHS_DEG).index(length) if length in FADE_LENGTHS_DEG else 0


def _decay_rank(weight_decay: float) -> float:
    """Stronger weight decays are simpler: -log10(wd), weight decay 0 last."""
    return -math.log10(weight_decay) if weight_decay > 0 else math.inf


@dataclass
class HeliostatChoice:
    """The sweep's outputs for one heliostat's choice.

    Attributes
    ----------
    selection : its selection.parquet row; state : its model file ({"state", "config"}; None
    for the coarse model); predictions : its selected_predictions rows; fallback : the static
    choice it falls back to when the forward check of
    :func:`apply_forward_checks` fails (None: a GP or the coarse model, checked already);
    time_errors : (N,) error_mrad of the model trained on the time split, where the selection
    knows it (the coarse model's from fit-coarse, a GP's refitted; None: a network's, which the
    sweep's forward pass trains); refused : the GP this choice stands in for, refused by the
    forward check (None: the rule's first choice). A network standing in must be checked
    forward: the sweep's forward pass trains it even without ``--time-split``.
    """

    selection: dict
    state: dict | None
    predictions: pd.DataFrame
    fallback: "HeliostatChoice | None" = None
    time_errors: np.ndarray | None = None
    refused: str | None = None


@dataclass
class CandidatePool:
    """One heliostat's candidates and the rule that chooses among them (module docstring).

    ``h`` is the sweep's heliostat (:class:`heliocal.pipeline.stages.sweep_inputs.SweepHeliostat`:
    its rows and labels, fit-coarse's selected fit and predictions, its time-split fit);
    ``screen`` and ``screen_gain`` its screen's verdict (:mod:`.sweep_screen`), written with the
    choice.
    """

    h: object
    rule: SelectionRule = SelectionRule()
    candidates: list = field(default_factory=list)
    screen: str = "off"
    screen_gain: float = math.nan

    def __post_init__(self):
        h = self.h
        self.val = h.labels == "validation"
        self.test = h.labels == "test"
        self.weights = row_validation_weights(h.rows, h.labels, self.rule.match_k,
                                              self.rule.match_share)
        self.coarse_errors = h.coarse[h.selected["preset"]]["error_mrad"].to_numpy(np.float64)
        base = Fade.of_rows(h.rows[h.train])
        self.fades = [base.with_lengths(length, NETWORK_TIME_FADE_DAYS)
                      for length in FADE_LENGTHS_DEG]
        self.fade_weights = [f.weights_of_rows(h.rows) for f in self.fades]

    # -------------------------------------------------------------------------------- adding
    def add_network(self, kind: str, cfg, weight_decay: float, seed: int, problem, layers,
                    path) -> tuple[np.ndarray, float]:
        """A hybrid ensemble (``layers`` of its K networks on ``problem``, the heliostat's rows):
        its fade chosen on the weighted validation rows; returns its errors (N,) there and the
        fade length [deg]."""
        errors = faded_errors_mrad(problem, layers, None, self.fade_weights)[:, 0]   # (L, N)
        k = choose_fade([e[self.val] for e in errors], self.weights) if self.val.any() else 0
        length = FADE_LENGTHS_DEG[k]
        self.candidates.append(Candidate(
            kind, errors[k][self.val],
            (2, _decay_rank(weight_decay), 0 if kind == "hybrid-octaves" else 1, _length_rank(length)),
            {"kind": "network", "weight_decay": float(weight_decay), "seed": int(seed),
             "errors": errors[k], "errors_by_length": errors, "fade": self.fades[k], "problem": problem, "cfg": cfg,
             "path": path, "layers": [(w.clone(), b.clone()) for w, b in layers],
             "date_inputs": True}))
        return errors[k], length

    def add_gp(self, fits: dict[str, HeliostatGP], gp_config: GPConfig
               ) -> list[tuple[str, HeliostatGP]]:
        """The GP of the highest marginal likelihood (``gp``), and its ``sun`` structure when
        that one has time (``gp-sun``; :func:`heliocal.pipeline.models.gp_heliostat.
        fit_heliostat_gps`); returns (name, fit) of each candidate added."""
        best = max(fits.values(), key=lambda f: f.model.log_marginal_likelihood)
        keep = [("gp", best)]
        if best.model.uses_time and "sun" in fits:
            keep.append(("gp-sun", fits["sun"]))
        for name, fit in keep:
            self.candidates.append(Candidate(
                name, fit.errors[self.val],
                (1, int(fit.model.uses_time), 0, _length_rank(fit.fade_length_deg)),
                {"kind": "gp", "weight_decay": float("nan"), "seed": gp_config.seed,
                 "errors": fit.errors, "errors_by_length": fit.errors_by_length, "fit": fit,
                 "gp_config": gp_config,
                 "date_inputs": fit.model.uses_time}))
        return keep

    def add_pretrained(self, model, info, normal, position, errors, seed: int,
                       pretrain_config) -> None:
        """The pre-trained network (paper 002), unfaded."""
        self.candidates.append(Candidate(
            "pretrained-nn", np.asarray(errors)[self.val], (3, 0, 0, 0),
            {"kind": "pretrained", "weight_decay": float("nan"), "seed": int(seed),
             "errors": np.asarray(errors), "model": model, "info": info, "normal": normal,
             "position": position, "pretrain_config": pretrain_config, "date_inputs": False}))

    # ------------------------------------------------------------------------------ choosing
    @property
    def n_compared(self) -> int:
        """The Bonferroni ``m``: every candidate, a faded one once per fade length tried."""
        return sum(len(FADE_LENGTHS_DEG) if c.info["kind"] != "pretrained" else 1
                   for c in self.candidates)

    def _pick(self, candidates) -> tuple[Candidate | None, Judgement | None]:
        if not self.val.any() or not candidates:
            return None, None
        variants = [e[self.val] for c in self.candidates
                    for e in c.info.get("errors_by_length", [c.info["errors"]])]
        k, judged = select(self.coarse_errors[self.val], candidates, self.weights, self.rule,
                           self.n_compared, variants)
        return (None, None) if k is None else (candidates[k], judged[k])

    def choose(self) -> HeliostatChoice:
        """The rule's choice, checked forward in time (module docstring): a GP, with or without
        time, is refitted on the time split here and, where it is worse there, gives way to the
        rule's next choice among the other candidates; a network gets the static choice as its
        :attr:`HeliostatChoice.fallback` for :func:`apply_forward_checks`."""
        chosen, judged, forward, refused = self._first_forward_choice()
        out = self._outputs(chosen, judged)
        if chosen is not None and chosen.info["kind"] != "gp":
            out.fallback = self._static_choice(exclude=refused)
            out.refused = None if refused is None else refused.model
        # the forward figures of the chosen GP, or behind another stand-in of the refused GP
        # (a network's own replace them after its forward pass)
        figures = forward if forward is not None else self._gp_forward(refused)
        if figures is not None:
            out.selection.update(time_val_error_mrad=figures[0],
                                 coarse_time_val_error_mrad=figures[1])
        if refused is not None:
            out.selection.update(forward_check=_refusal_label(refused.model, chosen))
        elif forward is not None:
            out.selection.update(forward_check="passed")
        return out

    def _first_forward_choice(self):
        """(chosen, judged, forward, refused): the rule's choice with every GP it prefers
        that the forward check refuses taken out of the running in turn, its forward figures
        (:meth:`_gp_forward`; None but for a GP) and ``refused`` the first GP taken out (None if
        none was). A network's check is left to :func:`apply_forward_checks`."""
        running = list(self.candidates)
        refused = None
        while True:
            chosen, judged = self._pick(running)
            forward = self._gp_forward(chosen)
            if forward is None or _no_worse(*forward):
                return chosen, judged, forward, refused
            refused = refused or chosen
            running.remove(chosen)

    def _static_choice(self, exclude: Candidate | None) -> HeliostatChoice:
        """What stands in for ``exclude`` where it is worse forward in time: the rule among the
        GPs without time input (other than ``exclude``) and the coarse model, each GP itself
        refitted on the time split and passed over where it is worse there, down to the coarse
        model. The networks are left out: their time-split training is the sweep's forward
        pass, made for the chosen model only, so a network could not be checked in its place."""
        static = [c for c in self.candidates if not c.info["date_inputs"] and c is not exclude
                  and c.info["kind"] == "gp"]
        while True:
            chosen, judged = self._pick(static)
            forward = self._gp_forward(chosen)
            if forward is None or _no_worse(*forward):
                return self._outputs(chosen, judged)
            static.remove(chosen)

    def _time_errors(self, chosen: Candidate) -> np.ndarray | None:
        """A GP's error_mrad (N,) trained on the time split (cached in its info); None without
        a time split or for other candidates (the sweep's forward pass trains those)."""
        if chosen.info["kind"] != "gp" or self.h.time_params is None:
            return None
        if "time_errors" not in chosen.info:
            labels = time_labels(self.h.rows, self.h.split_rows)
            chosen.info["time_errors"] = (None if labels is None else gp_time_errors(
                self.h, labels, self.h.time_params, chosen.info["fit"],
                chosen.info["gp_config"]))
        return chosen.info["time_errors"]

    def _gp_forward(self, chosen: Candidate | None) -> tuple[float, float] | None:
        """(the GP's, the coarse model's) mean error on the time split's validation rows, both
        trained on its training rows; None for a choice that is not a GP, without a time split
        or without time-split validation rows to judge on."""
        errors = None if chosen is None else self._time_errors(chosen)
        if errors is None:
            return None
        val = time_labels(self.h.rows, self.h.split_rows) == "validation"
        coarse = self.h.coarse[self.h.selected["preset"]]["time_error_mrad"].to_numpy(np.float64)
        forward = mean_or_nan(errors[val]), mean_or_nan(coarse[val])
        return forward if all(map(math.isfinite, forward)) else None

    # ------------------------------------------------------------------------------ outputs
    def _outputs(self, chosen: Candidate | None, judged: Judgement | None) -> HeliostatChoice:
        h = self.h
        w = self.weights
        coarse_w = float(np.sum(w * self.coarse_errors[self.val])) if self.val.any() else math.nan
        selection = {"heliostat_id": h.hid, "preset": h.selected["preset"], "n_train": h.n_full,
                     "coarse_val_error_mrad": h.coarse_val,
                     "coarse_test_error_mrad": h.coarse_test,
                     "coarse_weighted_val_error_mrad": coarse_w,
                     "n_candidates": self.n_compared, "screen": self.screen,
                     "screen_gain": self.screen_gain, "forward_check": "",
                     "time_val_error_mrad": math.nan, "coarse_time_val_error_mrad": math.nan}
        if chosen is None:
            selection.update(model="coarse", weight_decay=math.nan, seed=0,
                             val_error_mrad=h.coarse_val, test_error_mrad=h.coarse_test,
                             weighted_val_error_mrad=coarse_w, fade_length_deg=math.nan)
            coarse = h.coarse[h.selected["preset"]]
            return HeliostatChoice(selection, None, selected_frame(h, coarse),
                                   time_errors=coarse["time_error_mrad"].to_numpy(np.float64)
                                   if "time_error_mrad" in coarse else None)
        info = chosen.info
        errors = info["errors"]
        selection.update(model=chosen.model, weight_decay=info["weight_decay"],
                         seed=int(info["seed"]), val_error_mrad=mean_or_nan(errors[self.val]),
                         test_error_mrad=mean_or_nan(errors[self.test]),
                         weighted_val_error_mrad=judged.mean_mrad, fade_length_deg=math.nan)
        state, metrics = getattr(self, f"_{info['kind']}_state")(chosen)
        if "fade" in state["config"]:
            length = state["config"]["fade"]["length_deg"]
            selection["fade_length_deg"] = math.inf if length is None else float(length)
        return HeliostatChoice(selection, state, selected_frame(h, metrics),
                               time_errors=self._time_errors(chosen))

    def _common(self, mode: str, chosen: Candidate) -> dict:
        h = self.h
        return {"mode": mode, "heliostat_id": h.hid, "seed": int(chosen.info["seed"]),
                "variant": chosen.model, "coarse_preset": h.selected["preset"],
                "base_params": h.selected["params"].tolist(), "free": h.selected["free"].tolist(),
                "selected_by": "sweep"}

    def _network_state(self, chosen: Candidate):
        info = chosen.info
        problem, layers, cfg, fade = info["problem"], info["layers"], info["cfg"], info["fade"]
        with torch.no_grad():
            normal, position = predict_ensembles(problem, layers,
                                                 fade=fade.weights_of_rows(self.h.rows))
        config = {**self._common("hybrid", chosen), "weight_decay": info["weight_decay"],
                  "fine_config": cfg.to_dict(), "encoder": problem.encoder.to_dict(),
                  "scales": problem.scales.tolist(), "sizes": problem.sizes(cfg),
                  "path": info["path"].to_dict(), "fade": fade.to_dict()}
        return ({"state": layers_to_state(layers), "config": config},
                predictions_frame(problem, normal[0], position[0]))

    def _gp_state(self, chosen: Candidate):
        fit = chosen.info["fit"]
        config = {**self._common("gp", chosen), "gp_config": chosen.info["gp_config"].to_dict(),
                  "gp": fit.model.to_dict(), "fade": fit.model.fade.to_dict()}
        state = fit.model.to_state()
        return ({"state": state, "config": with_correction_map(config, state)},
                metrics_frame(self.h.data, fit.normal, fit.position))

    def _pretrained_state(self, chosen: Candidate):
        info = chosen.info
        model = info["model"]
        config = {"mode": "pretrained-nn", "heliostat_id": self.h.hid, "seed": int(info["seed"]),
                  "pretrain_config": info["pretrain_config"].to_dict(), **model.to_dict(),
                  "coarse_preset": self.h.selected["preset"], **info["info"],
                  "selected_by": "sweep"}
        return ({"state": model.to_state(), "config": config},
                metrics_frame(self.h.data, info["normal"], info["position"]))


def gp_time_errors(h, labels: np.ndarray, time_params: torch.Tensor, fit: HeliostatGP,
                   gp_config: GPConfig) -> np.ndarray:
    """error_mrad (N,) of every row of ``h`` under the GP of ``fit``'s structure and fade lengths
    fitted on the time split's training rows (``labels``; of a regime-aware model those of its
    latest regime, :func:`latest_regime_labels`) on top of fit-coarse's time-split
    parameters."""
    import dataclasses

    config = dataclasses.replace(gp_config, structures=(fit.model.structure,))
    labels = latest_regime_labels(h.selected, h.rows["timestamp"], labels)
    refit = fit_heliostat_gps(h.rows, labels, h.spec, h.data, time_params, config,
                              np.ones(int((labels == "validation").sum())),
                              lengths=(fit.fade_length_deg,),
                              time_length_days=fit.model.fade.length_days)
    return refit[fit.model.structure].errors


def latest_regime_labels(selected: dict, timestamps, labels: np.ndarray) -> np.ndarray:
    """The time split's ``labels`` (N,) of a heliostat's rows at UTC ``timestamps`` (N,) with
    the training rows before the latest regime of its selected model (``selected``: an entry of
    :func:`~heliocal.pipeline.stages.fit_coarse.load_selected_parameters`) left out
    (``unused``), where the model is regime-aware and that regime has at least
    :data:`~heliocal.pipeline.models.regime_fit.MIN_REGIME_ROWS` of them; else ``labels`` as
    they are.

    fit-coarse's time-split parameters of a regime-aware model are those of its latest regime
    (coarse_params.parquet ``time_fitted``). Under them the rows of earlier regimes carry the
    regimes' offsets and drift as a residual, which a GP refitted on them learns as a pattern
    of the sky or of the steps and carries into the later rows: on the simulated heliostats of
    docs/experiments/fine-selection.md it made the GP worse forward in time than the coarse
    model (SP34 0.55 against 0.47 mrad; 0.37 on the latest regime's rows alone)."""
    regimes = selected.get("regimes")
    if selected.get("regime_table") is None or regimes is None or not len(regimes):
        return labels
    starts = pd.to_datetime(regimes.loc[regimes["kind"] == "regime", "start"], utc=True)
    if starts.empty:
        return labels
    train = np.asarray(labels == "train", bool)
    earlier = train & (pd.to_datetime(pd.Series(timestamps), utc=True) < starts.max()).to_numpy()
    if int((train & ~earlier).sum()) < MIN_REGIME_ROWS:
        return labels
    return np.where(earlier, "unused", labels)


def study_gps(h, masks: dict, bases: dict, gp_config: GPConfig,
              rule: SelectionRule = SelectionRule()) -> dict[int, HeliostatGP]:
    """The training-size study's GP of one heliostat: per size ``n`` (its training rows
    ``masks[n]`` (N,), its coarse parameters ``bases[n]`` (28,)) the structure of the highest
    marginal likelihood, its fade chosen on the validation rows weighted as the selection's."""
    out = {}
    for n, mask in masks.items():
        labels = np.where(mask, "train", np.where(h.labels == "train", "unused", h.labels))
        weights = row_validation_weights(h.rows, labels, rule.match_k, rule.match_share)
        fits = fit_heliostat_gps(h.rows, labels, h.spec, h.data, bases[n], gp_config, weights,
                                 time_length_days=TIME_FADE_DAYS)
        out[n] = max(fits.values(), key=lambda f: f.model.log_marginal_likelihood)
    return out


def _refusal_label(gp_model: str, stand_in: Candidate | None) -> str:
    """selection.parquet's ``forward_check`` of a choice standing in for a refused GP: the
    coarse model, another GP (checked already) or a network, whose check is still to come
    (:func:`apply_forward_checks` completes the label)."""
    if stand_in is None:
        return f"failed ({gp_model}): fell back to the static choice"
    if stand_in.info["kind"] == "gp":
        return f"failed ({gp_model}), then passed ({stand_in.model})"
    return f"failed ({gp_model}): {stand_in.model} stands in"


def _no_worse(time_val: float, static_time_val: float) -> bool:
    """The forward check: a model's mean error on the time split's validation rows is at most
    the static choice's, within :data:`FORWARD_TOLERANCE`."""
    return time_val <= (1.0 + FORWARD_TOLERANCE) * static_time_val


def time_labels(rows: pd.DataFrame, split_rows: pd.DataFrame) -> np.ndarray | None:
    """split.parquet's ``time_split`` label of each of ``rows`` (object (N,); None where a row
    has none), or None when the heliostat has no usable time split (no column, fewer than two
    training rows or no validation row)."""
    if "time_split" not in split_rows.columns:
        return None
    by_id = dict(zip(split_rows["measurement_id"].astype(str), split_rows["time_split"]))
    labels = np.array([None if pd.isna(v := by_id.get(m)) else v
                       for m in rows["measurement_id"].astype(str)], dtype=object)
    return labels if (labels == "train").sum() >= 2 and (labels == "validation").any() else None


def _with_time_errors(choice: HeliostatChoice, labels: np.ndarray | None,
                      coarse_time: np.ndarray) -> HeliostatChoice:
    """The choice's predictions and selection with its forward-in-time errors (its own
    ``time_errors``), as the sweep's forward pass writes them."""
    err = choice.time_errors
    test = np.zeros(len(coarse_time), bool) if labels is None else labels == "test"
    choice.predictions["time_error_mrad"] = np.nan if err is None else err
    choice.selection["time_test_error_mrad"] = math.nan if err is None else mean_or_nan(err[test])
    choice.selection["coarse_time_test_error_mrad"] = mean_or_nan(coarse_time[test])
    return choice


def apply_forward_checks(results: list[dict], inputs: dict) -> None:
    """The forward-in-time check of the chosen networks, after the sweep's forward pass (in
    place; module docstring): a result whose choice has a static fallback (a hybrid, or the
    pre-trained network) keeps it when its mean error on the time split's validation rows is at
    most the coarse model's, else takes the fallback. Without its time-split errors (no time
    split, or a sweep without its forward pass) it is kept and ``forward_check`` says it was not
    checked. The label of a network standing in for a refused GP names both checks.

    ``inputs``: heliostat -> its :class:`heliocal.pipeline.stages.sweep_inputs.SweepInputs`.
    """
    for res in results:
        choice = res.get("choice")
        if choice is None or choice.fallback is None:
            continue
        item = inputs[res["selection"]["heliostat_id"]]
        rows = item.rows.reset_index(drop=True)
        coarse_time = item.coarse[item.selected["preset"]]["time_error_mrad"].to_numpy(np.float64)
        labels = time_labels(rows, item.split_rows)
        own = res["predictions"]["time_error_mrad"].to_numpy(np.float64) \
            if "time_error_mrad" in res["predictions"] else np.full(len(rows), np.nan)
        val = np.zeros(len(rows), bool) if labels is None else labels == "validation"
        figures = {"time_val_error_mrad": mean_or_nan(own[val]),
                   "coarse_time_val_error_mrad": mean_or_nan(coarse_time[val])}
        lead = "" if choice.refused is None else f"failed ({choice.refused}), then "
        if not all(map(math.isfinite, figures.values())):
            res["selection"].update(forward_check=f"{lead}not checked (no time-split training)",
                                    **figures)
            continue
        if _no_worse(figures["time_val_error_mrad"], figures["coarse_time_val_error_mrad"]):
            passed = "passed" if choice.refused is None else \
                f"{lead}passed ({res['selection']['model']})"
            res["selection"].update(forward_check=passed, **figures)
            continue
        back = _with_time_errors(choice.fallback, labels, coarse_time)
        back.selection.update(forward_check=f"{lead}failed ({res['selection']['model']}): fell "
                                            "back to the static choice", **figures)
        res.update(selection=back.selection, selected_state=back.state,
                   predictions=back.predictions, choice=back)
