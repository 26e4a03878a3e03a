"""Statistics over seeds: bootstrap intervals, IQM, probability of improvement and verdicts against hand-computed
truths and synthetic per-seed scores whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from socnav.experiments.statistics import (
    CANNOT_TELL, DOES_NOT_HOLD, HOLDS, Interval, compare, interquartile_mean, iqm_interval, mean_interval,
    probability_of_improvement, verdict,
)


def test_probability_of_improvement_counts_pairs_and_half_ties():
    # pairs (3,1) (3,2) (2,1) win, (2,2) ties: (3 + 0.5) / 4; a second task where y always wins: 0
    assert probability_of_improvement([[3.0, 2.0]], [[1.0, 2.0]]).estimate == pytest.approx(0.875)
    assert probability_of_improvement([[3.0, 2.0], [0.0]], [[1.0, 2.0], [5.0, 6.0]]).estimate == pytest.approx(0.4375)
    assert probability_of_improvement([[2.0]], [[2.0]]).estimate == 0.5


def test_interquartile_mean_trims_a_quarter_at_each_end():
    # 8 scores pooled over two tasks: the middle half is 2, 3, 4, 5
    assert float(interquartile_mean(np.array([7.0, 0.0, 5.0, 2.0]), np.array([1.0, 6.0, 3.0, 4.0]))) == 3.5
    assert iqm_interval([[7.0, 0.0, 5.0, 2.0], [1.0, 6.0, 3.0, 4.0]]).estimate == 3.5


def test_two_seeds_give_their_range_and_one_seed_no_interval():
    # resampled means of two seeds a < b are a, (a + b) / 2, b with probabilities 1/4, 1/2, 1/4: the 95 % percentile
    # interval is exactly [a, b]
    interval = mean_interval([40.0, 70.0])
    assert (interval.estimate, interval.low, interval.high) == (55.0, 40.0, 70.0)
    single = mean_interval([40.0])
    assert single.estimate == 40.0 and np.isnan(single.low) and np.isnan(single.high)
    assert verdict(single) == CANNOT_TELL and single.text(1) == "40.0 [n/a]"


def test_bootstrap_is_stratified_and_seeded():
    # seeds are resampled within each task: both tasks keep two runs, so the pooled mean cannot move
    constant = iqm_interval([[0.0, 0.0], [10.0, 10.0]])
    assert (constant.low, constant.high) == (5.0, 5.0)
    scores = [[1.0, 5.0, 2.0], [7.0, 3.0, 9.0]]
    assert iqm_interval(scores, seed=3) == iqm_interval(scores, seed=3)


def test_clearly_separated_algorithms():
    rng = np.random.default_rng(0)
    good = [rng.uniform(85, 95, 5) for _ in range(4)]  # 5 seeds x 4 cells
    bad = [rng.uniform(10, 30, 5) for _ in range(4)]
    result = compare(good, bad)
    assert result.improvement.estimate == 1.0 and result.improvement.low == 1.0
    assert result.verdict == HOLDS and result.difference.low > 50
    assert verdict(result.improvement, null=0.5) == HOLDS
    high, low = iqm_interval(good), iqm_interval(bad)
    assert low.high < high.low  # the intervals exclude each other
    reverse = compare(bad, good)
    assert reverse.verdict == DOES_NOT_HOLD and reverse.improvement.estimate == 0.0


def test_identical_algorithms_cannot_be_told_apart():
    rng = np.random.default_rng(1)
    scores = [rng.uniform(40, 90, 3) for _ in range(9)]  # 3 seeds, as the quick budget
    result = compare(scores, [s.copy() for s in scores])
    assert result.improvement.estimate == 0.5 and result.improvement.contains(0.5)
    assert result.difference.estimate == 0.0 and result.difference.contains(0.0)
    assert result.verdict == CANNOT_TELL


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
