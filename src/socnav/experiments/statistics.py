"""Statistics that can tell: confidence intervals over training seeds and verdicts on claims (Table 1 and docs).

The estimators follow Agarwal et al., *Deep RL at the Edge of the Statistical Precipice* (NeurIPS 2021), the
``rliable`` library: interval estimates come from a **stratified percentile bootstrap** -- the runs (here: training
seeds) are resampled with replacement *within* each task (here: a (training scenario, evaluation scenario) cell), so
every resample keeps every cell -- the aggregate score is the **interquartile mean** (IQM, the mean of the middle
50 % of all run x task scores, ``scipy.stats.trim_mean(scores, 0.25)`` as ``rliable.metrics.aggregate_iqm``) and
the **probability of improvement** ``P(X > Y)`` is, per task, the Mann-Whitney statistic ``P(x > y) + P(x = y)/2``
over all pairs of runs, averaged over tasks (as ``rliable.metrics.probability_of_improvement``).

We compute them with ``scipy.stats.bootstrap`` rather than ``rliable`` itself: ``rliable`` 1.2 needs ``arch < 8``,
whose releases do not import with pandas 3 (``arch`` 7.2 fails at import, ``arch`` 8 rejects the ``random_state``
``rliable`` passes), and its stratified bootstrap draws from NumPy's global generator, so its intervals are not
reproducible by a seed. ``scipy.stats.bootstrap`` given one sample per stratum resamples each independently, which
is exactly the stratified bootstrap; every function here takes a seed and is deterministic.

With very few seeds (2 or 3 at the quick budget) the percentile bootstrap interval of a mean cannot be wider than
the range of the seeds' values, so it *understates* the uncertainty: a "holds" verdict at such a budget is weaker
evidence than the same verdict with 10 seeds, and one seed gives no interval at all (NaN, "cannot tell").

Verdicts (:func:`verdict`): a claim "X is larger than Y" **holds** if the confidence interval of the difference
lies above the null value (0 for a difference, 0.5 for a probability of improvement), **does not hold** if it lies
below, and otherwise we **cannot tell at this budget**.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.stats

__all__ = [
    "CANNOT_TELL", "DOES_NOT_HOLD", "HOLDS", "Comparison", "Interval", "bootstrap_interval", "compare",
    "interquartile_mean", "iqm_interval", "mean_interval", "probability_of_improvement", "verdict",
]

HOLDS = "holds"
DOES_NOT_HOLD = "does not hold"
CANNOT_TELL = "cannot tell at this budget"

#: Bootstrap resamples: enough for stable 95 % percentile bounds (rliable's examples use 2,000 to 50,000).
DEFAULT_RESAMPLES = 5000
DEFAULT_CONFIDENCE = 0.95


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


Statistic = Callable[..., np.ndarray]


def _strata(samples: Sequence[Sequence[float]]) -> list[np.ndarray]:
    strata = [np.asarray(sample, dtype=np.float64).reshape(-1) for sample in samples]
    if not strata or any(len(stratum) == 0 for stratum in strata):
        raise ValueError("every stratum needs at least one run (score)")
    if any(np.isnan(stratum).any() for stratum in strata):
        raise ValueError("scores must not be NaN")
    return strata


def bootstrap_interval(samples: Sequence[Sequence[float]], statistic: Statistic,
                       confidence: float = DEFAULT_CONFIDENCE, n_resamples: int = DEFAULT_RESAMPLES,
                       seed: int = 0) -> Interval:
    """Stratified percentile bootstrap: each of ``samples`` (one per stratum) is resampled with replacement on its
    own; ``statistic(*samples, axis=-1)`` must be vectorised over leading axes. A stratum with a single run cannot
    vary, so with every stratum of size 1 the interval is undefined (NaN bounds)."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    strata = _strata(samples)
    estimate = float(statistic(*strata, axis=-1))
    varying = [index for index, stratum in enumerate(strata) if len(stratum) > 1]
    if not varying:
        return Interval(estimate, np.nan, np.nan)

    # scipy needs >= 2 runs per sample: strata of one run are constants, passed in unresampled.
    def resampled(*drawn: np.ndarray, axis: int = -1) -> np.ndarray:
        shape = drawn[0].shape[:-1]
        full = list(strata)
        for index, values in zip(varying, drawn):
            full[index] = values
        full = [np.broadcast_to(values, (*shape, len(values))) if values.ndim == 1 else values for values in full]
        return statistic(*full, axis=axis)

    result = scipy.stats.bootstrap(tuple(strata[index] for index in varying), resampled, vectorized=True,
                                   n_resamples=n_resamples, confidence_level=confidence, method="percentile",
                                   rng=np.random.default_rng(seed))
    low, high = result.confidence_interval
    return Interval(estimate, float(low), float(high))


def _concatenated_mean(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.concatenate(strata, axis=axis).mean(axis=axis)


def interquartile_mean(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
    """IQM of all scores of all strata pooled: the mean of the middle 50 % (25 % trimmed from each end)."""
    return scipy.stats.trim_mean(np.concatenate(strata, axis=axis), 0.25, axis=axis)


def mean_interval(scores: Sequence[float], confidence: float = DEFAULT_CONFIDENCE,
                  n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> Interval:
    """The mean of one cell's per-seed scores and its bootstrap interval over seeds."""
    return bootstrap_interval([scores], _concatenated_mean, confidence, n_resamples, seed)


def iqm_interval(scores_per_task: Sequence[Sequence[float]], confidence: float = DEFAULT_CONFIDENCE,
                 n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> Interval:
    """The IQM over all runs x tasks (``scores_per_task[t]``: the runs' scores on task t) and its stratified
    bootstrap interval (runs resampled within each task)."""
    return bootstrap_interval(scores_per_task, interquartile_mean, confidence, n_resamples, seed)


def _improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(x > y) + P(x = y) / 2 over all pairs of the last axes' runs (vectorised over leading axes)."""
    greater = (x[..., :, None] > y[..., None, :]).mean(axis=(-2, -1))
    equal = (x[..., :, None] == y[..., None, :]).mean(axis=(-2, -1))
    return greater + 0.5 * equal


def probability_of_improvement(scores_x: Sequence[Sequence[float]], scores_y: Sequence[Sequence[float]],
                               confidence: float = DEFAULT_CONFIDENCE, n_resamples: int = DEFAULT_RESAMPLES,
                               seed: int = 0) -> Interval:
    """Probability that a run of X beats a run of Y on the same task, averaged over tasks, and its interval.

    ``scores_x[t]`` / ``scores_y[t]``: the runs of X / Y on task t (the counts may differ). The two algorithms'
    runs are resampled independently within each task. 0.5: neither is better; 1: every run of X beats every run
    of Y on every task.
    """
    if len(scores_x) != len(scores_y) or not len(scores_x):
        raise ValueError(f"scores_x and scores_y need the same, non-zero number of tasks; got {len(scores_x)} "
                         f"and {len(scores_y)}")
    n_tasks = len(scores_x)

    def statistic(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.mean([_improvement(strata[t], strata[n_tasks + t]) for t in range(n_tasks)], axis=0)

    return bootstrap_interval([*scores_x, *scores_y], statistic, confidence, n_resamples, seed)


def _mean_difference(n_tasks: int) -> Statistic:
    def statistic(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.mean([strata[t].mean(axis=axis) - strata[n_tasks + t].mean(axis=axis) for t in range(n_tasks)],
                       axis=0)

    return statistic


@dataclass(frozen=True)
class Comparison:
    """A claim "X scores higher than Y", measured: the mean difference over tasks of the per-task mean over runs
    (``difference``), the probability of improvement, and the verdict from the difference's interval."""

    difference: Interval
    improvement: Interval
    verdict: str


def compare(scores_x: Sequence[Sequence[float]], scores_y: Sequence[Sequence[float]],
            confidence: float = DEFAULT_CONFIDENCE, n_resamples: int = DEFAULT_RESAMPLES,
            seed: int = 0) -> Comparison:
    """Test the claim "X > Y" on per-task run scores (as :func:`probability_of_improvement`): the verdict is
    :data:`HOLDS` if the interval of the mean difference lies above 0, :data:`DOES_NOT_HOLD` if below, and
    :data:`CANNOT_TELL` if it contains 0 (or is undefined). For a score where lower is better (e.g. the collision
    rate), test "X collides less than Y" as ``compare(scores_y, scores_x)``."""
    if len(scores_x) != len(scores_y) or not len(scores_x):
        raise ValueError(f"scores_x and scores_y need the same, non-zero number of tasks; got {len(scores_x)} "
                         f"and {len(scores_y)}")
    difference = bootstrap_interval([*scores_x, *scores_y], _mean_difference(len(scores_x)), confidence,
                                    n_resamples, seed)
    improvement = probability_of_improvement(scores_x, scores_y, confidence, n_resamples, seed)
    return Comparison(difference, improvement, verdict(difference, null=0.0))


def verdict(interval: Interval, null: float = 0.0) -> str:
    """The claim "the estimate is larger than ``null``": :data:`HOLDS` if the whole interval is above ``null``,
    :data:`DOES_NOT_HOLD` if it is below, :data:`CANNOT_TELL` if it contains ``null`` or is undefined (use
    ``null=0.5`` for a probability of improvement)."""
    if np.isnan(interval.low) or np.isnan(interval.high):
        return CANNOT_TELL
    if interval.low > null:
        return HOLDS
    if interval.high < null:
        return DOES_NOT_HOLD
    return CANNOT_TELL
