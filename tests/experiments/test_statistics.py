"""Statistics over trained policies: the stratified Welch test, the F-test, Holm and Bonferroni, and the descriptive
cluster-bootstrap intervals against hand-computed values, scipy's own tests and synthetic scores whose answer is
known."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from socnav.experiments.statistics import (
    CANNOT_TELL,
    DOES_NOT_HOLD,
    HOLDS,
    Interval,
    WelchTest,
    adjust_family,
    bonferroni_confidence,
    compare,
    compare_family,
    holm_adjust,
    interquartile_mean,
    iqm_interval,
    mean_interval,
    probability_of_improvement,
    variance_ratio_test,
    verdict,
    welch_test,
)


def test_probability_of_improvement_counts_pairs_and_half_ties():
    # pairs (3,1) (3,2) (2,1) win, (2,2) ties: (3 + 0.5) / 4; a second task where y always wins: 0
    assert probability_of_improvement([[3.0, 2.0]], [[1.0, 2.0]]).estimate == pytest.approx(0.875)
    assert probability_of_improvement([[3.0, 2.0], [0.0]], [[1.0, 2.0], [5.0, 6.0]]).estimate == pytest.approx(0.4375)
    assert probability_of_improvement([[2.0]], [[2.0]]).estimate == 0.5
    # a stratum of 2-cell policies: cell 1 as above (0.875), cell 2: x = 0, 9 vs y = 1, 1 -> 2 of 4 pairs win (0.5)
    x, y = np.array([[3.0, 0.0], [2.0, 9.0]]), np.array([[1.0, 1.0], [2.0, 1.0]])
    assert probability_of_improvement([x], [y]).estimate == pytest.approx((0.875 + 0.5) / 2)


def test_interquartile_mean_trims_a_quarter_at_each_end():
    # 8 scores pooled over two tasks: the middle half is 2, 3, 4, 5
    assert float(interquartile_mean(np.array([7.0, 0.0, 5.0, 2.0]), np.array([1.0, 6.0, 3.0, 4.0]))) == 3.5
    assert iqm_interval([[7.0, 0.0, 5.0, 2.0], [1.0, 6.0, 3.0, 4.0]]).estimate == 3.5


def test_mean_interval_is_the_student_t_interval():
    # two seeds 40, 70: mean 55, s = 21.21, s / sqrt(2) = 15, t_1(0.975) = 12.706: 55 -+ 190.6, far wider than the
    # seeds' range [40, 70] that a percentile bootstrap would give
    interval = mean_interval([40.0, 70.0])
    assert interval.estimate == 55.0
    assert (interval.low, interval.high) == pytest.approx((55.0 - 12.7062047 * 15.0, 55.0 + 12.7062047 * 15.0))
    scores = [81.0, 86.0, 90.0, 79.0, 84.0]
    low, high = scipy.stats.t.interval(0.9, 4, loc=np.mean(scores), scale=scipy.stats.sem(scores))
    assert (mean_interval(scores, 0.9).low, mean_interval(scores, 0.9).high) == pytest.approx((low, high))
    single = mean_interval([40.0])
    assert single.estimate == 40.0 and np.isnan(single.low) and np.isnan(single.high)
    assert verdict(single) == CANNOT_TELL and single.text(1) == "40.0 [n/a]"


def test_welch_test_on_one_stratum_is_scipys_welch_test():
    x, y = [71.0, 85.0, 80.0, 90.0], [60.0, 78.0, 66.0]
    ours = welch_test([x], [y])
    theirs = scipy.stats.ttest_ind(x, y, equal_var=False)
    assert ours.estimate == pytest.approx(np.mean(x) - np.mean(y))
    assert ours.estimate / ours.standard_error == pytest.approx(theirs.statistic)
    assert ours.df == pytest.approx(theirs.df) and ours.p_value == pytest.approx(theirs.pvalue)
    low, high = theirs.confidence_interval(0.9)
    assert (ours.interval(0.9).low, ours.interval(0.9).high) == pytest.approx((low, high))


def test_stratified_welch_by_hand_with_policies_as_clusters():
    # stratum A: 2 cells per policy; cluster means X 85, 75, 65 (mean 75, var 100), Y 65, 55, 75 (mean 65, var 100)
    # stratum B: 1 cell; X 90, 94 (mean 92, var 8), Y 88, 84, 86 (mean 86, var 4); weights = cells: 2/3, 1/3
    x = [np.array([[80.0, 90.0], [70.0, 80.0], [60.0, 70.0]]), np.array([90.0, 94.0])]
    y = [np.array([[60.0, 70.0], [50.0, 60.0], [70.0, 80.0]]), np.array([88.0, 84.0, 86.0])]
    # w² v / n of A's X (= A's Y), B's X, B's Y
    a, b, c = (2 / 3) ** 2 * 100 / 3, (1 / 3) ** 2 * 8 / 2, (1 / 3) ** 2 * 4 / 3
    result = welch_test(x, y)
    assert result.estimate == pytest.approx(2 / 3 * (75 - 65) + 1 / 3 * (92 - 86))  # 8.667
    assert result.standard_error ** 2 == pytest.approx(2 * a + b + c)  # 30.22
    assert result.df == pytest.approx((2 * a + b + c) ** 2 / (2 * a**2 / 2 + b**2 / 1 + c**2 / 2))  # 4.158
    assert result.p_value == pytest.approx(2 * scipy.stats.t.sf(result.estimate / result.standard_error, result.df))
    # a policy counts once however many cells it has: one stratum of 2-cell policies = Welch on the policies' means
    one = welch_test(x[:1], y[:1])
    direct = scipy.stats.ttest_ind([85.0, 75.0, 65.0], [65.0, 55.0, 75.0], equal_var=False)
    assert one.p_value == pytest.approx(direct.pvalue) and one.df == pytest.approx(direct.df)


def test_welch_edge_cases():
    assert np.isnan(welch_test([[80.0]], [[70.0, 75.0]]).p_value)  # one policy: no variance, no test
    assert verdict(welch_test([[80.0]], [[70.0, 75.0]]).interval()) == CANNOT_TELL
    exact = welch_test([[90.0, 90.0]], [[80.0, 80.0]])  # no spread at all: the difference is exact
    assert (exact.p_value, exact.interval().low, exact.interval().high) == (0.0, 10.0, 10.0)
    assert welch_test([[90.0, 90.0]], [[90.0, 90.0]]).p_value == 1.0
    with pytest.raises(ValueError, match="same cells"):
        welch_test([np.ones((2, 3))], [np.ones((2, 2))])


def test_variance_ratio_f_test_by_hand():
    # X: groups 1,2,3 and 10,12,14 -> squared deviations 2 + 8 over 2 + 2 df = 2.5; Y: 0,.5,1 and 5,5.5,6 -> 1 / 4
    result = variance_ratio_test([[1.0, 2.0, 3.0], [10.0, 12.0, 14.0]], [[0.0, 0.5, 1.0], [5.0, 5.5, 6.0]])
    assert (result.estimate, result.df_x, result.df_y) == (10.0, 4, 4)
    assert result.p_value == pytest.approx(2 * scipy.stats.f.sf(10.0, 4, 4))
    interval = result.interval(0.95)
    assert (interval.low, interval.high) == pytest.approx((10 / scipy.stats.f.ppf(0.975, 4, 4),
                                                           10 / scipy.stats.f.ppf(0.025, 4, 4)))
    assert verdict(interval, null=1.0) == HOLDS  # 1.04 > 1
    assert np.isnan(variance_ratio_test([[1.0]], [[1.0, 2.0]]).p_value)  # no degree of freedom for X


def test_holm_and_bonferroni_by_hand():
    # sorted p: 0.01, 0.015, 0.02, 0.30 times 4, 3, 2, 1 = 0.04, 0.045, 0.04, 0.30, then running maximum
    adjusted = holm_adjust([0.01, 0.02, 0.015, 0.30])
    np.testing.assert_allclose(adjusted, [0.04, 0.045, 0.045, 0.30])
    # Holm rejects three at 0.05, Bonferroni (p x 4 <= 0.05) only the first
    assert list(adjusted <= 0.05) == [True, True, True, False]
    assert list(np.array([0.01, 0.02, 0.015, 0.30]) * 4 <= 0.05) == [True, False, False, False]
    np.testing.assert_allclose(holm_adjust([0.01, np.nan, 0.02]), [0.02, np.nan, 0.02])  # untestable: not counted
    assert holm_adjust([0.6, 0.9]).tolist() == [1.0, 1.0]
    assert bonferroni_confidence(0.95, 4) == pytest.approx(0.9875)

    tests = [WelchTest(3.0, 1.0, 10.0, 0.01), WelchTest(-2.0, 1.0, 10.0, 0.02), WelchTest(1.0, 1.0, 10.0, 0.015),
             WelchTest(0.5, 1.0, 10.0, 0.30), WelchTest(np.nan, np.nan, np.nan, np.nan)]
    results = adjust_family(tests)
    assert [r.verdict for r in results] == [HOLDS, DOES_NOT_HOLD, HOLDS, CANNOT_TELL, CANNOT_TELL]
    assert all(r.confidence == pytest.approx(0.9875) for r in results)  # K = 4 testable claims
    assert results[0].interval.low == pytest.approx(3.0 - scipy.stats.t.ppf(1 - 0.0125 / 2, 10.0))
    # Holm is decisive for the third although its Bonferroni interval (1 -+ 3.04) contains 0
    assert results[2].interval.contains(0.0) and results[2].p_adjusted == pytest.approx(0.045)


def test_cluster_bootstrap_resamples_whole_policies():
    # policies resampled within each stratum: both strata keep two policies, so the pooled mean cannot move
    constant = iqm_interval([[0.0, 0.0], [10.0, 10.0]])
    assert (constant.low, constant.high) == (5.0, 5.0)
    # a policy good in one cell and bad in the other is one unit: every resample pools {0, 10, 0, 10} or the like
    paired = iqm_interval([np.array([[0.0, 10.0], [10.0, 0.0]])])
    assert (paired.estimate, paired.low, paired.high) == (5.0, 5.0, 5.0)
    scores = [[1.0, 5.0, 2.0], [7.0, 3.0, 9.0]]
    assert iqm_interval(scores, seed=3) == iqm_interval(scores, seed=3)


def test_clearly_separated_algorithms():
    rng = np.random.default_rng(0)
    good = [rng.uniform(85, 95, (5, 3)) for _ in range(3)]  # 3 training scenarios x 5 policies x 3 cells
    bad = [rng.uniform(10, 30, (5, 3)) for _ in range(3)]
    result = compare(good, bad)
    assert result.improvement.estimate == 1.0 and result.improvement.low == 1.0
    assert result.verdict == HOLDS and result.difference.low > 50 and result.p_value < 1e-6
    assert verdict(result.improvement, null=0.5) == HOLDS
    high, low = iqm_interval(good), iqm_interval(bad)
    assert low.high < high.low  # the intervals exclude each other
    reverse = compare(bad, good)
    assert reverse.verdict == DOES_NOT_HOLD and reverse.improvement.estimate == 0.0
    # the Bonferroni level widens the interval with the number of claims, never moves the estimate
    wide = compare(good, bad, n_claims=10)
    assert wide.confidence == pytest.approx(0.995) and wide.difference.low < result.difference.low
    family = compare_family([(good, bad), (bad, good), (good, [g.copy() for g in good])])
    assert [c.verdict for c in family] == [HOLDS, DOES_NOT_HOLD, CANNOT_TELL]
    assert family[0].confidence == pytest.approx(1 - 0.05 / 3)


def test_identical_algorithms_cannot_be_told_apart():
    rng = np.random.default_rng(1)
    scores = [rng.uniform(40, 90, 3) for _ in range(9)]  # 3 seeds, as the quick budget
    result = compare(scores, [s.copy() for s in scores])
    assert result.improvement.estimate == 0.5 and result.improvement.contains(0.5)
    assert result.difference.estimate == 0.0 and result.difference.contains(0.0)
    assert result.verdict == CANNOT_TELL and result.p_value == pytest.approx(1.0)


def test_verdict_and_errors():
    assert verdict(Interval(1.0, 0.5, 1.5)) == HOLDS
    assert verdict(Interval(-1.0, -1.5, -0.5)) == DOES_NOT_HOLD
    assert verdict(Interval(0.2, -0.1, 0.5)) == CANNOT_TELL
    assert verdict(Interval(0.7, 0.55, 0.9), null=0.5) == HOLDS
    with pytest.raises(ValueError, match="same, non-zero number of tasks"):
        compare([[1.0]], [[1.0], [2.0]])
    with pytest.raises(ValueError, match="at least one run"):
        mean_interval([])
    with pytest.raises(ValueError, match="confidence must be in"):
        mean_interval([1.0, 2.0], confidence=1.5)
    with pytest.raises(ValueError, match="must not be NaN"):
        welch_test([[1.0, np.nan]], [[1.0, 2.0]])
