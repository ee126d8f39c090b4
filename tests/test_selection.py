"""The selection rule (models/selection.py): distance-matched validation weights, the paired gain
and its standard error, the Bonferroni margin and the one-standard-error preference.

Expected values are worked out by hand in the comments.
"""

import math

import numpy as np
import pandas as pd
import pytest

from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.models.selection import (Candidate, SelectionRule, choose_fade,
                                                max_t_threshold, paired_gain,
                                                row_validation_weights, select,
                                                validation_weights)


def test_weights_put_the_validation_rows_where_the_test_rows_are():
    # validation rows at 1, 2, 3, 10 deg from training, test rows at 9 and 11 deg. k=1: both test
    # rows' nearest validation distance is 10. k=2: each spreads 1/2 over 10 and 3 (gaps 1 and 6,
    # 1 and 8): weights (0, 0, 1, 1) / 2
    assert validation_weights([1, 2, 3, 10], [9, 11], k=1).tolist() == [0, 0, 0, 1]
    assert validation_weights([1, 2, 3, 10], [9, 11], k=2).tolist() == [0, 0, 0.5, 0.5]
    # k 0 or no test distances: equal weights
    assert validation_weights([1, 2, 3, 10], [9, 11], k=0).tolist() == [0.25] * 4
    assert validation_weights([1, 2], [], k=3).tolist() == [0.5, 0.5]
    # half matched, half equal: 0.5 * (0, 0, 0.5, 0.5) + 0.5 / 4
    assert validation_weights([1, 2, 3, 10], [9, 11], k=2, share=0.5).tolist() == \
        [0.125, 0.125, 0.375, 0.375]


def test_row_weights_measure_distances_from_the_rows_sun_positions():
    # train at azimuth 0 and 10 (elevation 30); validation at azimuth 12 (2 deg away) and 30
    # (20 deg), test at 28 (18 deg): k=1 puts all weight on the validation row at 30
    rows = pd.DataFrame({"sun_azimuth_deg": [0.0, 10.0, 12.0, 30.0, 28.0],
                         "sun_elevation_deg": [30.0] * 5})
    labels = np.array(["train", "train", "validation", "validation", "test"], dtype=object)
    assert row_validation_weights(rows, labels, k=1).tolist() == [0.0, 1.0]


def test_paired_gain_and_its_standard_error():
    # gains 1, 2, 3, 4 with equal weights: mean 2.5, sample sd sqrt(5/3) = 1.2910, se sd / 2
    coarse = np.array([5.0, 5.0, 5.0, 5.0])
    d, se, base = paired_gain(coarse, coarse - [1, 2, 3, 4], np.full(4, 0.25))
    assert (d, base) == pytest.approx((2.5, 5.0))
    assert se == pytest.approx(math.sqrt(5 / 3) / 2, rel=1e-12)
    # all the weight on one row: no spread to estimate from
    assert paired_gain(coarse, coarse - 1, [1, 0, 0, 0])[1] == math.inf


def test_the_bonferroni_quantile():
    # Phi^-1(0.95) = 1.6449, Phi^-1(1 - 0.05 / 10) = Phi^-1(0.995) = 2.5758 (normal tables)
    assert SelectionRule(alpha=0.05).z(1) == pytest.approx(1.644854, abs=1e-6)
    assert SelectionRule(alpha=0.05).z(10) == pytest.approx(2.575829, abs=1e-6)
    assert SelectionRule(alpha=1.0).z(10) == -math.inf


def _candidate(model, errors, complexity):
    return Candidate(model, np.asarray(errors, float), complexity)


def test_select_keeps_the_simplest_candidate_within_one_standard_error():
    rng = np.random.default_rng(0)
    coarse = np.full(20, 1.0)
    w = np.full(20, 1 / 20)
    noise = rng.normal(0, 0.02, 20)
    simple = _candidate("gp", 0.70 + noise, (1,))          # 30 % better, consistently
    complex_ = _candidate("hybrid", 0.69 + noise, (3,))      # 0.01 mrad better still
    small = _candidate("hybrid", 0.95 + noise, (2,))         # 5 %: below the 10 % margin
    noisy = _candidate("hybrid", 0.70 + rng.normal(0, 1.5, 20), (2,))   # not significant
    rule = SelectionRule(min_improvement=0.1, alpha=0.05, multiplicity="bonferroni")
    kept, judged = select(coarse, [complex_, small, noisy, simple], w, rule)
    assert [j.passed for j in judged] == [True, False, False, True]
    # the best's se (its errors' and, the coarse errors being constant, its gain's) is the
    # noise's sd / sqrt(20), about 0.0045 mrad: `simple` is 0.01 mrad (more than one se) worse
    # than the best, `complex_`, which is kept
    se = judged[0].se_mrad
    assert se == pytest.approx(np.std(noise, ddof=1) / math.sqrt(20), rel=1e-9)
    assert se < 0.01 and kept == 0
    # with the two 0.003 mrad apart (within one se) the simpler one is kept
    close = _candidate("hybrid", 0.697 + noise, (3,))
    kept, _ = select(coarse, [close, simple], w, rule)
    assert kept == 1
    # nothing passes: the coarse model stays
    assert select(coarse, [small, noisy], w, rule)[0] is None


def test_the_one_se_band_is_the_best_s_own_standard_error_not_its_gain_s():
    # a dynamic heliostat's coarse errors alternate 0.2 / 0.9 mrad from row to row; the best
    # candidate is 0.25 mrad on every row up to +-0.01, a simpler one 0.08 mrad worse. The
    # best's gain over the coarse model then has a standard error of sd(0.2/0.9 pattern) /
    # sqrt(20) = 0.0826 mrad, its errors one of 0.01 * sqrt(20/19) / sqrt(20) = 0.0023 mrad
    n = 20
    coarse = np.tile([0.2, 0.9], n // 2)
    wiggle = np.tile([0.01, -0.01], n // 2)
    best = _candidate("hybrid", 0.25 + wiggle, (3,))
    simple = _candidate("hybrid", 0.33 + wiggle, (2,))
    w = np.full(n, 1 / n)
    base = dict(min_improvement=0.1, alpha=1.0)
    judged = select(coarse, [best, simple], w, SelectionRule(**base))[1]
    assert all(j.passed for j in judged)                         # 55 % and 40 % better
    assert judged[0].se_mrad == pytest.approx(np.std(coarse - best.val_errors, ddof=1)
                                              / math.sqrt(n), rel=1e-9)
    assert judged[0].se_mrad == pytest.approx(0.0826, abs=1e-4)
    # the default band, 0.25 + 0.0023 mrad, leaves the simpler candidate out: the best is kept
    assert SelectionRule().one_se_of == "error"
    assert select(coarse, [best, simple], w, SelectionRule(**base))[0] == 0
    # the gain's band, 0.25 + 0.0826 mrad, takes in a candidate 32 % worse on every row
    assert select(coarse, [best, simple], w, SelectionRule(**base, one_se_of="gain"))[0] == 1
    # the paired difference (0.08 on every row, no spread) keeps the best too
    assert select(coarse, [best, simple], w,
                  SelectionRule(**base, one_se_of="difference"))[0] == 0
    # within the best's own se the simpler one is kept: 0.002 mrad worse
    near = _candidate("hybrid", 0.252 + wiggle, (2,))
    assert select(coarse, [best, near], w, SelectionRule(**base))[0] == 1


def test_the_relative_margin_grows_with_the_candidates_flexibility():
    # 15 % better on every row: enough for the GP (10 %), not for a network (20 %)
    coarse, w = np.full(20, 1.0), np.full(20, 0.05)
    errors = 0.85 + np.random.default_rng(5).normal(0, 0.01, 20)
    rule = SelectionRule(alpha=1.0)
    assert select(coarse, [_candidate("gp", errors, (1,))], w, rule)[0] == 0
    assert select(coarse, [_candidate("hybrid", errors, (2,))], w, rule)[0] is None
    assert select(coarse, [_candidate("gp-sun", errors, (1,))], w, rule)[0] == 0


def test_never_worse_than_the_coarse_model_on_the_plain_validation_mean():
    # 30 % better on the three far rows that carry the weight, 10 % worse on the other 17: the
    # weighted mean gains, the plain mean loses (0.3 * 0.3 * 3 < 0.1 * 17 per row of 1 mrad)
    coarse = np.full(20, 1.0)
    errors = np.r_[np.full(17, 1.1), np.full(3, 0.7)]
    w = np.r_[np.full(17, 0.01), np.full(3, 0.83 / 3)]
    rule = SelectionRule(alpha=1.0, min_improvement_gp=0.0)
    kept, judged = select(coarse, [_candidate("gp", errors, (1,))], w, rule)
    assert judged[0].gain_mrad > 0 and kept is None


def test_many_candidates_raise_the_margin():
    # gains of 0.05 +- 0.1 mrad over 20 rows: t = 0.05 / (0.1 / sqrt(20)) = 2.24 before the
    # noise; significant against one candidate (z 1.64), not against 100 (z 3.29)
    rng = np.random.default_rng(1)
    g = rng.normal(0, 1, 20)
    g = 0.05 + 0.1 * (g - g.mean()) / g.std(ddof=1)
    coarse = np.full(20, 0.4)
    c = _candidate("gp", coarse - g, (1,))
    rule = SelectionRule(min_improvement=0.0, multiplicity="bonferroni")
    w = np.full(20, 0.05)
    assert select(coarse, [c], w, rule)[0] == 0
    assert select(coarse, [c], w, rule, n_candidates=100)[0] is None


def test_max_t_counts_correlated_candidates_once_and_independent_ones_in_full():
    # one candidate: the sign-flip quantile of a studentised mean of 20 rows, about Student's
    # t_0.95 with 19 degrees of freedom (1.73); twenty copies of it (perfectly correlated, like
    # the weight-decay path's neighbours) give exactly the same margin, twenty independent ones
    # a larger one (a Bonferroni bound would put 20 copies at Phi^-1(1 - 0.05/20) = 2.81)
    rng = np.random.default_rng(3)
    coarse, w = np.full(20, 1.0), np.full(20, 0.05)
    one = [coarse - rng.normal(0.0, 0.1, 20)]
    single = max_t_threshold(coarse, one, w, 0.05)
    assert 1.4 < single < 2.0
    assert max_t_threshold(coarse, one * 20, w, 0.05) == pytest.approx(single, rel=1e-12)
    independent = [coarse - rng.normal(0.0, 0.1, 20) for _ in range(20)]
    assert max_t_threshold(coarse, independent, w, 0.05) > single + 0.5
    # seeded: the same margin again
    assert max_t_threshold(coarse, independent, w, 0.05) == \
        max_t_threshold(coarse, independent, w, 0.05)


def test_choose_fade_takes_the_lowest_weighted_mean_and_ties_go_shorter():
    w = np.array([0.5, 0.5])
    assert choose_fade([np.array([1.0, 1.0]), np.array([0.8, 1.0]), np.array([1.0, 0.9])], w) == 1
    assert choose_fade([np.array([1.0, 1.0]), np.array([1.0, 1.0])], w) == 1


def test_rule_settings_are_checked():
    with pytest.raises(ParameterError, match=r"The 'one_se_of' parameter of select must be one "
                                             r"of gain, error, difference. Got 'se' instead."):
        SelectionRule(one_se_of="se").validated()
    with pytest.raises(ParameterError, match=r"The 'alpha' parameter of select must be"):
        SelectionRule(alpha=0.0).validated()
    with pytest.raises(ParameterError, match=r"The 'weights' parameter of select must have one "
                                             r"weight per validation row \(3\). Got 2 instead."):
        select(np.ones(3), [], np.ones(2))
