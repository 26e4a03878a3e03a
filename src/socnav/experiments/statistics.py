"""Statistics that keep their error rate: tests, confidence intervals and verdicts on claims over trained policies.
Table 1's report (:mod:`socnav.experiments.report`) and the power analysis (:mod:`socnav.experiments.power`) use it.

**The unit is the trained policy.** Table 1 trains one policy per (training scenario, algorithm, seed) and evaluates
it in every evaluation scenario, so its scores in those cells share the policy's luck: they are one *cluster*, not
independent runs. Every function here takes scores as **strata of clusters**: a list with one 2-D array per stratum
(a training scenario), rows = clusters (policies, i.e. training seeds), columns = the stratum's cells (evaluation
scenarios); a 1-D array is a stratum of one-cell clusters (the clusters of different strata are independent).

**The test** (:func:`welch_test`, what every verdict of a difference rests on): each cluster is reduced to its mean
over the stratum's cells, ``c_k``; per stratum ``s`` and algorithm ``g`` the clusters give a mean ``m_sg``, a
variance ``v_sg`` (ddof=1) and a count ``n_sg``; with ``w_s`` = the stratum's share of all cells::

    D   = sum_s w_s (m_sX - m_sY)                          (= the mean over cells of the difference of cell means)
    SE² = sum_s w_s² (v_sX / n_sX + v_sY / n_sY)
    df  = SE⁴ / sum_s,g (w_s² v_sg / n_sg)² / (n_sg - 1)    (Welch-Satterthwaite)
    t   = D / SE,   p = 2 P(T_df > |t|),   interval = D ± t_df(1 - a/2) SE

With one stratum of one-cell clusters this is Welch's t-test (``scipy.stats.ttest_ind(x, y, equal_var=False)``).
Its coverage rests on the clusters' means being roughly normal, not on many of them: it holds at 3 seeds, where a
percentile bootstrap cannot (its interval is never wider than the seeds' range). A group with fewer than 2 clusters
in a stratum has no variance: no interval (NaN), *cannot tell*. If every variance is 0 the interval is the point.
In the null simulation of Table 1's design (:mod:`socnav.experiments.power` at the seed variation measured in our
quick run: policies sharing their luck across 3 cells, binomial episodes) it gives a decisive verdict in 3.7 % of
null cases at 3 seeds and 4.9 % at 15; the stratified percentile bootstrap with cells as independent strata, used
before, in 22 % and 16 % (11 % and 6 % even if every cell had its own policy).

**Spread across seeds** (:func:`variance_ratio_test`): the variance over clusters pooled over groups (sum of squared
deviations from each group's mean / sum of ``n_g - 1``) of two sets of groups, compared by the F-test: ratio
``F = s²_X / s²_Y`` with ``(df_X, df_Y)`` degrees of freedom, interval ``[F / f(1 - a/2), F / f(a/2)]``. Exact for
normal scores with one spread per set; not robust to heavy tails (a single failed seed), which the report says.

**Several claims in one table** (:func:`adjust_family`): with K tests, every interval is shown at the Bonferroni
level ``1 - a/K`` (all K intervals cover together with probability >= 1 - a) and the verdicts come from Holm's
step-down adjustment of the two-sided p-values (:func:`holm_adjust`): the family-wise rate of false verdicts stays
<= a under any dependence. Holm rejects everything Bonferroni rejects and sometimes more, so a verdict can be
decisive while its Bonferroni interval still touches the null; the adjusted p-value shows why.

**Verdicts**: a claim "X is larger than Y" **holds** if the (adjusted) test rejects "no difference" and the estimate
is above the null (0 for a difference, 1 for a variance ratio), **does not hold** if it rejects and the estimate is
below, and otherwise we **cannot tell at this budget**. "Does not hold" means the opposite was shown, not merely
that the claim was not.

**Descriptive statistics** (no verdict rests on them): the interquartile mean (IQM, ``rliable``'s aggregate, the
mean of the middle 50 % of all cluster x cell scores) and the probability of improvement ``P(X > Y)`` (per cell the
Mann-Whitney statistic ``P(x > y) + P(x = y) / 2`` over pairs of clusters, averaged over cells), with percentile
intervals from a **cluster bootstrap**: whole clusters resampled with replacement within each stratum. With 3
clusters per stratum those intervals understate the uncertainty; they are shown, never tested.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.stats
from numpy.typing import ArrayLike

__all__ = [
    "CANNOT_TELL", "DOES_NOT_HOLD", "HOLDS", "AdjustedTest", "Comparison", "Interval", "VarianceRatioTest",
    "WelchTest", "adjust_family", "bonferroni_confidence", "cluster_bootstrap_interval", "compare", "compare_family",
    "holm_adjust", "interquartile_mean", "iqm_interval", "mean_interval", "probability_of_improvement",
    "stratified_welch", "variance_ratio_test", "verdict", "welch_test",
]

HOLDS = "holds"
DOES_NOT_HOLD = "does not hold"
CANNOT_TELL = "cannot tell at this budget"

#: Bootstrap resamples of the descriptive intervals (rliable's examples use 2,000 to 50,000).
DEFAULT_RESAMPLES = 5000
DEFAULT_CONFIDENCE = 0.95

Scores = Sequence[Sequence[float]] | Sequence[np.ndarray]


@dataclass(frozen=True)
class Interval:
    """A point estimate and its confidence interval (NaN bounds: not enough runs for an interval)."""

    estimate: float
    low: float
    high: float

    def contains(self, value: float) -> bool:
        """Whether ``value`` lies in the closed interval (True when the interval is undefined: NaN bounds)."""
        if np.isnan(self.low) or np.isnan(self.high):
            return True
        return self.low <= value <= self.high

    def text(self, decimals: int = 2) -> str:
        """``estimate [low, high]``; ``estimate [n/a]`` without an interval."""
        if np.isnan(self.estimate):
            return "–"
        if np.isnan(self.low) or np.isnan(self.high):
            return f"{self.estimate:.{decimals}f} [n/a]"
        return f"{self.estimate:.{decimals}f} [{self.low:.{decimals}f}, {self.high:.{decimals}f}]"


# --------------------------------------------------------------------------------------------------------------
# Scores as strata of clusters
# --------------------------------------------------------------------------------------------------------------

def _strata(scores: Scores) -> list[np.ndarray]:
    """Each stratum as a float array (clusters, cells); a 1-D stratum is one column."""
    strata = []
    for stratum in scores:
        array = np.asarray(stratum, dtype=np.float64)
        if array.ndim == 1:
            array = array[:, None]
        if array.ndim != 2 or array.shape[0] == 0 or array.shape[1] == 0:
            raise ValueError("every stratum needs at least one run (score): a 1-D array of runs or a 2-D array "
                             f"(clusters, cells); got shape {array.shape}")
        if np.isnan(array).any():
            raise ValueError("scores must not be NaN")
        strata.append(array)
    if not strata:
        raise ValueError("every stratum needs at least one run (score); got no strata")
    return strata


def _paired_strata(scores_x: Scores, scores_y: Scores) -> tuple[list[np.ndarray], list[np.ndarray]]:
    if len(scores_x) != len(scores_y) or not len(scores_x):
        raise ValueError(f"scores_x and scores_y need the same, non-zero number of tasks; got {len(scores_x)} "
                         f"and {len(scores_y)}")
    strata_x, strata_y = _strata(scores_x), _strata(scores_y)
    for x, y in zip(strata_x, strata_y, strict=True):
        if x.shape[1] != y.shape[1]:
            raise ValueError(f"X and Y must be scored on the same cells of a stratum; got {x.shape[1]} and "
                             f"{y.shape[1]} cells")
    return strata_x, strata_y


# --------------------------------------------------------------------------------------------------------------
# One mean, and the difference of two: t-intervals
# --------------------------------------------------------------------------------------------------------------

def mean_interval(scores: Sequence[float], confidence: float = DEFAULT_CONFIDENCE) -> Interval:
    """The mean of independent scores (one cell's per-seed scores) and its Student t-interval
    ``mean ± t_{n-1}(1 - a/2) s / sqrt(n)`` (NaN bounds with one score)."""
    _check_confidence(confidence)
    values = _strata([scores])[0][:, 0]
    mean = float(values.mean())
    if len(values) < 2:
        return Interval(mean, np.nan, np.nan)
    half_width = scipy.stats.t.ppf(0.5 + confidence / 2, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values))
    return Interval(mean, float(mean - half_width), float(mean + half_width))


def _check_confidence(confidence: float) -> None:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")


def stratified_welch(means_x: np.ndarray, variances_x: np.ndarray, counts_x: np.ndarray, means_y: np.ndarray,
                     variances_y: np.ndarray, counts_y: np.ndarray, weights: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(D, SE, df)`` of the stratified Welch test from per-stratum moments of the cluster means (last axis:
    strata; leading axes are vectorised over, as the power simulation needs). See the module docstring."""
    weights = np.asarray(weights, dtype=np.float64)
    estimate = np.sum(weights * (means_x - means_y), axis=-1)
    # each group's share of the variance of D: w_s² v_sg / n_sg
    share_x = weights**2 * variances_x / counts_x
    share_y = weights**2 * variances_y / counts_y
    variance = np.sum(share_x + share_y, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        df = variance**2 / np.sum(share_x**2 / (counts_x - 1) + share_y**2 / (counts_y - 1), axis=-1)
    return estimate, np.sqrt(variance), df


@dataclass(frozen=True)
class WelchTest:
    """The stratified Welch test of "X and Y have the same mean" (null 0): estimate ``D``, its standard error,
    Welch-Satterthwaite degrees of freedom and two-sided p-value (NaN: untestable, a group has < 2 clusters)."""

    estimate: float
    standard_error: float
    df: float
    p_value: float
    null: float = 0.0
    method: str = "stratified Welch t-test, a policy = one unit"

    def interval(self, confidence: float = DEFAULT_CONFIDENCE) -> Interval:
        """``D ± t_df(1 - a/2) SE`` (the point when SE is 0, NaN bounds when untestable)."""
        _check_confidence(confidence)
        if np.isnan(self.standard_error):
            return Interval(self.estimate, np.nan, np.nan)
        if self.standard_error == 0.0:
            return Interval(self.estimate, self.estimate, self.estimate)
        half_width = float(scipy.stats.t.ppf(0.5 + confidence / 2, self.df)) * self.standard_error
        return Interval(self.estimate, self.estimate - half_width, self.estimate + half_width)


def welch_test(scores_x: Scores, scores_y: Scores) -> WelchTest:
    """Stratified Welch test of the mean difference X - Y over cells, clusters as units (see the module docstring).

    ``scores_x[s]`` / ``scores_y[s]``: stratum s as a 2-D array (clusters, cells) or 1-D array of one-cell clusters;
    both on the same cells of each stratum, with any numbers of clusters.
    """
    strata_x, strata_y = _paired_strata(scores_x, scores_y)
    cells = np.array([x.shape[1] for x in strata_x], dtype=np.float64)
    weights = cells / cells.sum()
    # a cluster counts once: its mean over the stratum's cells
    cluster_means_x = [x.mean(axis=1) for x in strata_x]
    cluster_means_y = [y.mean(axis=1) for y in strata_y]
    counts_x = np.array([len(c) for c in cluster_means_x], dtype=np.float64)
    counts_y = np.array([len(c) for c in cluster_means_y], dtype=np.float64)
    means_x = np.array([c.mean() for c in cluster_means_x])
    means_y = np.array([c.mean() for c in cluster_means_y])
    estimate = float(np.sum(weights * (means_x - means_y)))
    if min(counts_x.min(), counts_y.min()) < 2:
        return WelchTest(estimate, np.nan, np.nan, np.nan)
    variances_x = np.array([c.var(ddof=1) for c in cluster_means_x])
    variances_y = np.array([c.var(ddof=1) for c in cluster_means_y])
    estimate, standard_error, df = (float(v) for v in stratified_welch(
        means_x, variances_x, counts_x, means_y, variances_y, counts_y, weights))
    if standard_error == 0.0:
        # every cluster of a group scores alike: the difference is exact (or exactly 0)
        return WelchTest(estimate, 0.0, np.nan, 1.0 if estimate == 0.0 else 0.0)
    p_value = float(2 * scipy.stats.t.sf(abs(estimate) / standard_error, df))
    return WelchTest(estimate, standard_error, df, p_value)


# --------------------------------------------------------------------------------------------------------------
# Spread across seeds: the F-test of a variance ratio
# --------------------------------------------------------------------------------------------------------------

def _pooled_variance(groups: Sequence[ArrayLike]) -> tuple[float, int]:
    """Sum of squared deviations from each group's mean / sum of (n_g - 1), and that sum (the df)."""
    arrays = [np.asarray(g, dtype=np.float64).reshape(-1) for g in groups]
    if any(np.isnan(a).any() for a in arrays):
        raise ValueError("scores must not be NaN")
    squares = sum(float(np.sum((a - a.mean()) ** 2)) for a in arrays if len(a))
    df = sum(len(a) - 1 for a in arrays if len(a))
    return (squares / df if df > 0 else np.nan), df


@dataclass(frozen=True)
class VarianceRatioTest:
    """The F-test of "X and Y spread alike" (null ratio 1): ``estimate = s²_X / s²_Y`` with its degrees of freedom
    and two-sided p-value (NaN: a set has no degree of freedom, or both have no spread)."""

    estimate: float
    df_x: int
    df_y: int
    p_value: float
    null: float = 1.0
    method: str = "F-test of pooled within-group variances"

    def interval(self, confidence: float = DEFAULT_CONFIDENCE) -> Interval:
        """``[F / f(1 - a/2), F / f(a/2)]`` of the F(df_x, df_y) distribution."""
        _check_confidence(confidence)
        if np.isnan(self.p_value) or not np.isfinite(self.estimate):
            return Interval(self.estimate, np.nan, np.nan)
        upper_quantile = scipy.stats.f.ppf(0.5 + confidence / 2, self.df_x, self.df_y)
        lower_quantile = scipy.stats.f.ppf(0.5 - confidence / 2, self.df_x, self.df_y)
        return Interval(self.estimate, float(self.estimate / upper_quantile), float(self.estimate / lower_quantile))


def variance_ratio_test(groups_x: Sequence[ArrayLike], groups_y: Sequence[ArrayLike]
                        ) -> VarianceRatioTest:
    """F-test of the spread of X's scores against Y's. ``groups_x``: X's scores in groups (e.g. one per algorithm)
    whose means may differ; the spread is the pooled within-group variance (see the module docstring)."""
    variance_x, df_x = _pooled_variance(groups_x)
    variance_y, df_y = _pooled_variance(groups_y)
    if df_x < 1 or df_y < 1 or (variance_x == 0.0 and variance_y == 0.0):
        return VarianceRatioTest(np.nan, df_x, df_y, np.nan)
    with np.errstate(divide="ignore"):
        ratio = variance_x / variance_y
    below = scipy.stats.f.cdf(ratio, df_x, df_y)
    p_value = float(min(1.0, 2 * min(below, 1.0 - below)))
    return VarianceRatioTest(float(ratio), df_x, df_y, p_value)


# --------------------------------------------------------------------------------------------------------------
# Several claims: Holm's verdicts, Bonferroni's intervals
# --------------------------------------------------------------------------------------------------------------

def holm_adjust(p_values: ArrayLike) -> np.ndarray:
    """Holm's step-down adjusted p-values: sorted ascending, the j-th (from 0) becomes
    ``max_{i <= j} min(1, (K - i) p_(i))``; a test is rejected at family-wise level a iff its adjusted p <= a.
    NaN p-values (untestable claims) stay NaN and do not count in K."""
    p_values = np.asarray(p_values, dtype=np.float64)
    adjusted = np.full_like(p_values, np.nan)
    testable = np.flatnonzero(~np.isnan(p_values))
    order = testable[np.argsort(p_values[testable], kind="stable")]
    n_tests = len(order)
    scaled = np.minimum(1.0, (n_tests - np.arange(n_tests)) * p_values[order])
    adjusted[order] = np.maximum.accumulate(scaled)  # step-down: never smaller than an earlier (smaller) p
    return adjusted


def bonferroni_confidence(confidence: float, n_claims: int) -> float:
    """The per-interval confidence ``1 - (1 - confidence) / K`` that makes K intervals cover together."""
    _check_confidence(confidence)
    return 1.0 - (1.0 - confidence) / max(int(n_claims), 1)


def verdict(interval: Interval, null: float = 0.0) -> str:
    """The claim "the estimate is larger than ``null``": :data:`HOLDS` if the whole interval is above ``null``,
    :data:`DOES_NOT_HOLD` if it is below, :data:`CANNOT_TELL` if it contains ``null`` or is undefined (use
    ``null=0.5`` for a probability of improvement, 1 for a ratio)."""
    if np.isnan(interval.low) or np.isnan(interval.high):
        return CANNOT_TELL
    if interval.low > null:
        return HOLDS
    if interval.high < null:
        return DOES_NOT_HOLD
    return CANNOT_TELL


def _verdict_from_test(estimate: float, adjusted_p: float, null: float, alpha: float) -> str:
    if np.isnan(adjusted_p) or adjusted_p > alpha or estimate == null:
        return CANNOT_TELL
    return HOLDS if estimate > null else DOES_NOT_HOLD


@dataclass(frozen=True)
class AdjustedTest:
    """One test of a family: its Bonferroni-level interval, raw and Holm-adjusted p-values, and the verdict."""

    interval: Interval
    confidence: float
    p_value: float
    p_adjusted: float
    verdict: str


def adjust_family(tests: Sequence[WelchTest | VarianceRatioTest], confidence: float = DEFAULT_CONFIDENCE
                  ) -> list[AdjustedTest]:
    """Verdicts on K claims with family-wise error <= 1 - ``confidence``: Holm on the p-values for the verdicts,
    intervals at the Bonferroni level (K = the number of testable claims)."""
    alpha = 1.0 - confidence
    p_values = np.array([t.p_value for t in tests], dtype=np.float64)
    adjusted = holm_adjust(p_values)
    level = bonferroni_confidence(confidence, int(np.sum(~np.isnan(p_values))))
    return [AdjustedTest(test.interval(level), level, float(test.p_value), float(p_adjusted),
                         _verdict_from_test(test.estimate, p_adjusted, test.null, alpha))
            for test, p_adjusted in zip(tests, adjusted, strict=True)]


# --------------------------------------------------------------------------------------------------------------
# Descriptive: IQM and probability of improvement with cluster-bootstrap intervals
# --------------------------------------------------------------------------------------------------------------

def cluster_bootstrap_interval(strata: Scores, statistic: Callable[[list[np.ndarray]], np.ndarray],
                               confidence: float = DEFAULT_CONFIDENCE, n_resamples: int = DEFAULT_RESAMPLES,
                               seed: int = 0) -> Interval:
    """Percentile interval of ``statistic`` when whole clusters (rows) are resampled with replacement within each
    stratum. ``statistic(arrays)`` gets one array (resamples, clusters, cells) per stratum and returns one value per
    resample. No stratum with 2+ clusters: no interval (NaN bounds)."""
    _check_confidence(confidence)
    arrays = _strata(strata)
    estimate = float(statistic([a[None] for a in arrays])[0])
    if all(len(a) == 1 for a in arrays):
        return Interval(estimate, np.nan, np.nan)
    rng = np.random.default_rng(seed)
    resampled = [a[rng.integers(0, len(a), size=(n_resamples, len(a)))] for a in arrays]
    values = statistic(resampled)
    low, high = np.quantile(values, [0.5 - confidence / 2, 0.5 + confidence / 2])
    return Interval(estimate, float(low), float(high))


def interquartile_mean(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
    """IQM of all scores of all strata pooled: the mean of the middle 50 % (25 % trimmed from each end)."""
    return scipy.stats.trim_mean(np.concatenate(strata, axis=axis), 0.25, axis=axis)


def _pooled_iqm(resampled: list[np.ndarray]) -> np.ndarray:
    pooled = np.concatenate([r.reshape(r.shape[0], -1) for r in resampled], axis=1)
    return scipy.stats.trim_mean(pooled, 0.25, axis=1)


def iqm_interval(scores: Scores, confidence: float = DEFAULT_CONFIDENCE, n_resamples: int = DEFAULT_RESAMPLES,
                 seed: int = 0) -> Interval:
    """The IQM over all clusters x cells and its cluster-bootstrap interval (descriptive). ``scores[s]``: stratum s,
    2-D (clusters, cells) or 1-D (one-cell clusters, e.g. one task's runs)."""
    return cluster_bootstrap_interval(scores, _pooled_iqm, confidence, n_resamples, seed)


def _improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per cell, P(x > y) + P(x = y) / 2 over all pairs of clusters: x (B, n_x, cells), y (B, n_y, cells) ->
    (B, cells)."""
    greater = (x[:, :, None, :] > y[:, None, :, :]).mean(axis=(1, 2))
    equal = (x[:, :, None, :] == y[:, None, :, :]).mean(axis=(1, 2))
    return greater + 0.5 * equal


def probability_of_improvement(scores_x: Scores, scores_y: Scores, confidence: float = DEFAULT_CONFIDENCE,
                               n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> Interval:
    """Probability that a cluster (policy) of X beats one of Y in the same cell, averaged over all cells, and its
    cluster-bootstrap interval (X's and Y's clusters resampled independently within each stratum; descriptive).
    0.5: neither is better; 1: every policy of X beats every policy of Y in every cell."""
    strata_x, strata_y = _paired_strata(scores_x, scores_y)
    n_strata = len(strata_x)

    def statistic(resampled: list[np.ndarray]) -> np.ndarray:
        per_cell = [_improvement(resampled[s], resampled[n_strata + s]) for s in range(n_strata)]
        return np.concatenate(per_cell, axis=1).mean(axis=1)

    return cluster_bootstrap_interval([*strata_x, *strata_y], statistic, confidence, n_resamples, seed)


# --------------------------------------------------------------------------------------------------------------
# A comparison of two algorithms, and a family of them
# --------------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Comparison:
    """A claim "X scores higher than Y", measured: the mean difference over cells (``difference``, at confidence
    ``confidence``), the probability of improvement (descriptive, nominal confidence), the verdict, and the test's
    p-value (raw and, in a family, Holm-adjusted) and degrees of freedom."""

    difference: Interval
    improvement: Interval
    verdict: str
    p_value: float = np.nan
    p_adjusted: float = np.nan
    df: float = np.nan
    confidence: float = DEFAULT_CONFIDENCE


def compare(scores_x: Scores, scores_y: Scores, confidence: float = DEFAULT_CONFIDENCE, n_claims: int = 1,
            n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> Comparison:
    """Test the claim "X > Y" (scores as strata of clusters, see the module docstring) with the stratified Welch
    test; the difference's interval is at the Bonferroni level for ``n_claims`` claims and the verdict is read from
    it (:data:`HOLDS` above 0, :data:`DOES_NOT_HOLD` below, else :data:`CANNOT_TELL`). For several claims of one
    table prefer :func:`compare_family` (Holm). For a score where lower is better (e.g. the collision rate), test
    "X collides less than Y" as ``compare(scores_y, scores_x)``."""
    test = welch_test(scores_x, scores_y)
    level = bonferroni_confidence(confidence, n_claims)
    difference = test.interval(level)
    improvement = probability_of_improvement(scores_x, scores_y, confidence, n_resamples, seed)
    p_adjusted = min(1.0, test.p_value * max(n_claims, 1)) if not np.isnan(test.p_value) else np.nan
    return Comparison(difference, improvement, verdict(difference, null=0.0), test.p_value, p_adjusted, test.df,
                      level)


def compare_family(pairs: Sequence[tuple[Scores, Scores]], confidence: float = DEFAULT_CONFIDENCE,
                   n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> list[Comparison]:
    """:func:`compare` for every (X scores, Y scores) of one table: intervals at the Bonferroni level, verdicts by
    Holm, so the table's family-wise rate of false verdicts is <= 1 - ``confidence``."""
    tests = [welch_test(x, y) for x, y in pairs]
    adjusted = adjust_family(tests, confidence)
    return [Comparison(result.interval, probability_of_improvement(x, y, confidence, n_resamples, seed),
                       result.verdict, result.p_value, result.p_adjusted, test.df, result.confidence)
            for (x, y), test, result in zip(pairs, tests, adjusted, strict=True)]
