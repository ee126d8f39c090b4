"""The sweep's training-size study with fit-coarse's field prior (issue 34, part 5).

Expected values and their sources:

* a study point is what fit-coarse gives with that many rows: the study's refit of a preset at
  its smallest size must equal a direct :func:`fit_presets` of that heliostat on those rows
  under the very prior fit-coarse gave it (captured from fit-coarse's own call, not rebuilt
  the way the study rebuilds it), to floating-point noise (1e-9 mrad: same function, same
  inputs, same order of operations); without the prior the same for ``+no-field-prior``;
* at 5 training rows the field prior lowers the error: docs/experiments/field-prior.md's 5-row
  tables (the simulated fields with ``--mounting field``: kNN test mean 0.815 -> 0.507 mrad and
  0.697 -> 0.453 mrad; the CSV log 3.69 -> 1.97 mrad), so the median over the study
  heliostats of the selected base preset's test error must be lower with the prior;
* the prior rebuilt from coarse_params.parquet is the prior fit-coarse used, entry for entry
  on the free parameters (those a fit moves; a fixed one stays at the prior's mean, the
  nominal value in both).
"""

from __future__ import annotations

import numpy as np
import pytest

from heliocal.pipeline.artifacts.schemas import COARSE_PARAMS, SWEEP
from heliocal.pipeline.artifacts.store import read_artifact
from heliocal.pipeline.models.coarse import normal_errors_mrad
from heliocal.pipeline.models.coarse_presets import fit_presets
from heliocal.pipeline.models.config import FineConfig, ScreenConfig
from heliocal.pipeline.models.prior_noise import HeliostatPrior
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.stages import fit_coarse as fit_coarse_module
from heliocal.pipeline.stages.fit_coarse import coarse_fit_options, run_fit_coarse
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.stages.simulate import write_field
from heliocal.pipeline.stages.split import restrict_training, run_split
from heliocal.pipeline.stages.study_prior import heliostat_priors, prior_rows_of
from heliocal.pipeline.stages.sweep import run_sweep
from heliocal.pipeline.stages.sweep_inputs import SweepHeliostat, read_sweep_inputs

pytestmark = pytest.mark.slow

SIZES = [5, 10]


@pytest.fixture(scope="module")
def studied(tmp_path_factory):
    """The fixture field of tests/test_field_prior_stage.py, fit-coarse under the field prior
    (its priors captured from its own fit_presets calls), then a small sweep with a study of
    two heliostats."""
    tmp = tmp_path_factory.mktemp("study-prior")
    field = simulate_field(20, seed=11, measurements=(12, 70), mounting="field",
                           noise_mrad=0.2, dynamic_fraction=0.0)
    write_field(field, tmp / "sim")
    work = tmp / "work"
    run_ingest([tmp / "sim" / "paint"], work)
    run_split(work, n_test=20, n_val=10)
    used: dict = {}
    real = fit_coarse_module.fit_presets

    def spy(specs, nominals, trains, presets, **kwargs):
        for hid, by_preset in (kwargs.get("priors") or {}).items():
            used.setdefault(hid, {}).update(by_preset)
        return real(specs, nominals, trains, presets, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fit_coarse_module, "fit_presets", spy)
        run_fit_coarse(work, preset="auto", prior="field", rolling_origins=0)
    summary = run_sweep(work, n_train=SIZES, weight_decays=[0.0], seeds=[0], baselines=(),
                        config=FineConfig(max_epochs=10, patience=10, ensemble=1),
                        extra_bands=(), study=2, gp=False, screen=ScreenConfig(enabled=False))
    return work, used, summary["study_heliostats"]


def test_the_study_refits_under_the_prior_fit_coarse_gave_each_heliostat(studied):
    work, used, ids = studied
    assert len(ids) == 2 and all(h in used for h in ids)
    sweep = read_artifact(work, SWEEP)
    items = read_sweep_inputs(work, ids)
    options = coarse_fit_options(work)
    rows_of = prior_rows_of(work, ids)
    for hid in ids:
        h = SweepHeliostat.of(items[hid])
        rebuilt = heliostat_priors(rows_of[hid], h.nominal)
        assert set(rebuilt) == set(used[hid])
        for preset, prior in used[hid].items():
            assert isinstance(prior, HeliostatPrior) and prior.field is not None
            at = rows_of[hid].loc[rows_of[hid]["preset"] == preset, "parameter_index"]
            at = at.to_numpy(int)
            for got, want in zip(rebuilt[preset], prior):
                np.testing.assert_array_equal(np.asarray(got)[at], np.asarray(want)[at])
        # the smallest size, directly: the selected base preset under the captured prior
        n = SIZES[0]
        restricted = restrict_training(h.split_rows, n)
        train_ids = set(restricted.loc[restricted["split"] == "train", "measurement_id"])
        mask = h.rows["measurement_id"].isin(train_ids).to_numpy()
        assert mask.sum() == n
        preset = h.selected["base_preset"]
        for priors, model in (({hid: used[hid]}, preset), (None, f"{preset}+no-field-prior")):
            fit = fit_presets([h.spec], [h.nominal], [h.data.subset(mask)], [preset],
                              priors=priors, **options)[0][0]
            err = normal_errors_mrad(fit.params, h.spec, h.data).numpy()
            row = sweep[(sweep["heliostat_id"] == hid) & (sweep["model"] == model)
                        & (sweep["n_train"] == n)]
            assert len(row) == 1
            for split, column in (("test", "test_error_mrad"), ("validation", "val_error_mrad"),
                                  ("train", "train_error_mrad")):
                sel = mask if split == "train" else (h.labels == split)
                assert row[column].iloc[0] == pytest.approx(float(err[sel].mean()), abs=1e-9)


def test_the_prior_lowers_the_five_row_error_and_both_curves_reach_the_full_size(studied):
    work, _, ids = studied
    sweep = read_artifact(work, SWEEP)
    params = read_artifact(work, COARSE_PARAMS)
    chosen = params[params["selected"]].drop_duplicates("heliostat_id").set_index("heliostat_id")
    with_prior, without = [], []
    for hid in ids:
        preset = str(chosen.loc[hid, "preset"]).split("+")[0]
        mine = sweep[sweep["heliostat_id"] == hid]
        full = int(chosen.loc[hid, "n_train"])
        for model in (preset, f"{preset}+no-field-prior"):
            assert sorted(mine.loc[mine["model"] == model, "n_train"]) == SIZES + [full]
        at5 = mine[mine["n_train"] == 5].set_index("model")["test_error_mrad"]
        with_prior.append(at5[preset])
        without.append(at5[f"{preset}+no-field-prior"])
    print("5 rows, test mean [mrad] with / without the prior:", with_prior, without)
    assert np.median(with_prior) < np.median(without)
    # no +no-field-prior model outside the study, and none at all for the hybrids
    assert set(sweep.loc[sweep["model"].str.endswith("+no-field-prior"), "heliostat_id"]) == set(ids)

