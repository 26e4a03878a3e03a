"""Stage 2 of the calibration: the selection by rollouts, replaying the calibration episodes with each proposed
rule's :class:`~socnav.safety.SafePolicy` and keeping the one that prevents the most within the budget, measured.

The proxy of stage 1 is optimistic (the cautious controller may still collide, or cause a later collision) and its
records come from the plain policy's trajectories. :func:`select_by_rollouts` therefore measures both what a
candidate prevents and how often its fallback acts where nothing was perturbed, in real rollouts, and bounds the
latter from above (:func:`false_activation_upper`) before comparing it with the budget.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

import numpy as np
import pandas as pd

from socnav.safety.rule import Thresholds
from socnav.safety.triggers import SafetyDecision, decision_fields, never_fires

__all__ = [
    "CalibrationRun",
    "clopper_pearson_upper",
    "false_activation_upper",
    "ratio_and_standard_error",
    "rollout_scores",
    "select_by_rollouts",
]


@dataclass(frozen=True)
class CalibrationRun:
    """One configuration of calibration episodes: ``n_episodes`` episodes, episode k from seed ``seed + k``;
    ``group`` names the perturbation type (runs of one type are pooled when scoring)."""

    config: Any
    perturbed: bool
    n_episodes: int
    seed: int
    group: str = "perturbed"


def _restart(estimator: Any) -> None:
    restart = getattr(estimator, "restart", None)
    if callable(restart):  # a seeded MC-dropout estimator: every candidate sees the same mask stream
        restart()


def rollout_scores(thresholds: SafetyDecision | None, policy: Any, estimator: Any, runs: Sequence[CalibrationRun],
                   window: int = 4, n_envs: int = 40,
                   progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Collisions and fallback activations of real rollouts on ``runs``: the plain ``policy`` if ``thresholds``
    is None, else :class:`~socnav.safety.SafePolicy` with them. ``progress(n)``: n more episodes finished.

    :return: ``collisions`` (dict group -> count over the perturbed runs' episodes of that group),
        ``false_activation_rate`` (fallback steps / steps over the unperturbed runs; 0 for the plain policy), its
        standard error ``false_activation_se``, and the counts ``false_activation_steps`` and ``unperturbed_steps``.
    """
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety.safe_policy import FallbackCounter, SafePolicy

    collisions: dict[str, int] = {}
    lengths: list[np.ndarray] = []
    fallbacks_per_episode: list[np.ndarray] = []
    for run in runs:
        if thresholds is None:
            records = rollout_episodes(policy, run.config, run.n_episodes, seed=run.seed, n_envs=n_envs,
                                       progress=progress)
            fallbacks = np.zeros(len(records))
        else:
            _restart(estimator)
            safe = SafePolicy(policy, estimator, thresholds, run.config, window=window)
            counter = FallbackCounter(safe)
            records = rollout_episodes(safe, run.config, run.n_episodes, seed=run.seed, n_envs=n_envs,
                                       observer=counter, progress=progress)
            fallbacks = np.asarray(counter.per_episode(records["episode"]), dtype=np.float64)
        if run.perturbed:
            collisions[run.group] = collisions.get(run.group, 0) + int((records["outcome"] == "collision").sum())
        else:
            lengths.append(records["length"].to_numpy(np.float64))
            fallbacks_per_episode.append(fallbacks)
    counts = np.concatenate(fallbacks_per_episode) if fallbacks_per_episode else np.zeros(0)
    steps = np.concatenate(lengths) if lengths else np.zeros(0)
    rate, standard_error = ratio_and_standard_error(counts, steps)
    return {"collisions": collisions, "false_activation_rate": rate, "false_activation_se": standard_error,
            "false_activation_steps": int(counts.sum()), "unperturbed_steps": int(steps.sum())}


def clopper_pearson_upper(events: int, trials: int, confidence: float = 0.95) -> float:
    """Exact (Clopper-Pearson) one-sided upper confidence bound of a binomial proportion after ``events`` in
    ``trials``: the p at which seeing at most ``events`` has probability ``1 - confidence``, i.e. the
    ``confidence`` quantile of Beta(events + 1, trials - events); 1 when every trial is an event. Unlike the
    normal approximation it is not 0 after 0 events: 1 - (1 - confidence)^(1 / trials), about 3 / trials at 95 %.
    """
    from scipy.stats import beta

    if trials < 1:
        return 1.0
    if not 0 <= events <= trials:
        raise ValueError(f"events must be in [0, trials={trials}], got {events}")
    if events == trials:
        return 1.0
    return float(beta.ppf(confidence, events + 1, trials - events))


def false_activation_upper(scores: Mapping[str, Any], confidence: float) -> float:
    """One-sided upper bound of a measured false-activation rate (``rollout_scores`` output): the larger of the
    normal bound ``rate + z SE`` with episodes as the independent units (wide when activations cluster in a few
    episodes) and the exact Clopper-Pearson bound on the step counts (not 0 when no step fired, where the normal
    bound collapses to the point estimate). ``confidence = 0.5``: the point estimate."""
    rate = float(scores["false_activation_rate"])
    if confidence <= 0.5:
        return rate
    normal = rate + NormalDist().inv_cdf(confidence) * float(scores["false_activation_se"])
    exact = clopper_pearson_upper(int(scores["false_activation_steps"]), int(scores["unperturbed_steps"]),
                                  confidence)
    return max(normal, exact)


def ratio_and_standard_error(counts: np.ndarray, lengths: np.ndarray) -> tuple[float, float]:
    """Steps-weighted rate ``sum(counts) / sum(lengths)`` over episodes and its standard error, episodes being the
    independent units (steps of one episode are not): the ratio estimator's linearised variance,
    ``SE^2 = sum((c_i - r n_i)^2) / (m (m - 1) mean(n)^2)``. NaN for both without steps; an infinite SE from a
    single episode."""
    m, total = len(lengths), float(lengths.sum())
    if m == 0 or total == 0:
        return float("nan"), float("nan")
    rate = float(counts.sum()) / total
    if m < 2:
        return rate, float("inf")
    residual = counts - rate * lengths
    return rate, float(np.sqrt((residual ** 2).sum() / (m * (m - 1))) / lengths.mean())


def _check_selection(candidates: Sequence[SafetyDecision], runs: Sequence[CalibrationRun], confidence: float,
                     plain_collisions: Mapping[str, int] | None) -> None:
    if not candidates:
        raise ValueError("select_by_rollouts needs at least one candidate")
    if not 0.5 <= confidence < 1.0:
        raise ValueError(f"confidence must be in [0.5, 1), got {confidence}")
    if not any(run.perturbed for run in runs) or all(run.perturbed for run in runs):
        raise ValueError("runs need both perturbed (collisions to prevent) and unperturbed (false activations) runs")
    if plain_collisions is not None:
        expected = {run.group for run in runs if run.perturbed}
        if set(plain_collisions) != expected:
            raise ValueError(f"plain_collisions has the perturbation types {sorted(plain_collisions)}, the runs "
                             f"{sorted(expected)}: measure them on these runs")


def select_by_rollouts(candidates: Sequence[SafetyDecision], policy: Any, estimator: Any,
                       runs: Sequence[CalibrationRun], false_activation_budget: float = 0.05, window: int = 4,
                       n_envs: int = 40, confidence: float = 0.95,
                       progress: Callable[[int], None] | None = None,
                       plain_collisions: Mapping[str, int] | None = None,
                       cache: dict[Any, dict[str, Any]] | None = None) -> tuple[SafetyDecision, pd.DataFrame]:
    """Stage 2: the candidate that prevents the most collisions in REAL rollouts on the calibration ``runs``, among
    those whose measured false-activation rate (unperturbed runs) is within ``false_activation_budget`` with
    ``confidence``: its one-sided upper bound (:func:`false_activation_upper`: the larger of the normal bound
    ``rate + z * SE``, episodes as the independent units, and the exact Clopper-Pearson bound on the steps;
    ``confidence = 0.5`` uses the point estimate) must not exceed the budget. ``progress(n)``: n more episodes
    replayed (``len(candidates) + 1`` passes over ``runs``; ``len(candidates)`` with ``plain_collisions``). A few
    dozen calibration episodes estimate the rate only roughly; without the margin, a rule chosen at the edge of the
    budget can exceed it on new episodes.

    Per perturbation type (``CalibrationRun.group``) with plain-policy collisions, prevented fraction =
    (plain collisions - safe collisions) / plain collisions on the same episode seeds (a rule that causes
    collisions scores lower); candidates are ranked by the WORST type's fraction (``prevented_worst``), then by the
    MEAN over types (``prevented_fraction``), so that no perturbation type is traded for another (pooled counts
    would let the type with the most collisions decide; see `socnav.safety.calibration.proxy_search`). Further ties
    go to the lower false-activation rate, then to the earlier candidate. If no candidate meets the budget,
    thresholds that never fire are returned (the layer is then off). Deterministic given a deterministic policy and
    a seeded estimator.

    ``plain_collisions``: the plain policy's collisions per type on these ``runs`` (``rollout_scores(None, ...)``'s
    ``collisions``) if already measured: the plain pass is then skipped. ``cache``: ``rollout_scores`` of
    candidates already replayed on these ``runs`` (thresholds -> scores), read and extended: a candidate found there
    is not replayed again (the replays are deterministic, so the numbers are the same).

    :return: ``(thresholds, table)``: one row per candidate with ``prevented_worst`` and ``prevented_fraction``
        (the score, lexicographically), one ``prevented_<group>`` column per type, ``false_activation_rate``,
        ``false_activation_upper`` and ``chosen``.
    """
    _check_selection(candidates, runs, confidence, plain_collisions)
    plain = (dict(plain_collisions) if plain_collisions is not None
             else rollout_scores(None, policy, estimator, runs, window, n_envs, progress)["collisions"])
    groups = [group for group, count in plain.items() if count > 0]
    rows = []
    for index, thresholds in enumerate(candidates):
        if cache is not None and thresholds in cache:
            scores = cache[thresholds]
        else:
            scores = rollout_scores(thresholds, policy, estimator, runs, window, n_envs, progress)
            if cache is not None:
                cache[thresholds] = scores
        per_group = {group: (plain[group] - scores["collisions"][group]) / plain[group] for group in groups}
        rows.append({**decision_fields(thresholds), "candidate": index, "plain_collisions": sum(plain.values()),
                     "safe_collisions": sum(scores["collisions"].values()),
                     "prevented_fraction": float(np.mean(list(per_group.values()))) if groups else float("nan"),
                     "prevented_worst": float(np.min(list(per_group.values()))) if groups else float("nan"),
                     **{f"prevented_{group}": value for group, value in per_group.items()},
                     "false_activation_rate": scores["false_activation_rate"],
                     # A rule that cannot fire has no false activation to be uncertain about.
                     "false_activation_upper": (0.0 if never_fires(thresholds)
                                                else false_activation_upper(scores, confidence))})
    table = pd.DataFrame(rows)
    table.attrs["plain_collisions"] = plain
    feasible = table["false_activation_upper"] <= false_activation_budget + 1e-12
    table["chosen"] = False
    if not feasible.any() or not groups:
        return Thresholds.never(), table
    ranked = table[feasible].sort_values(["prevented_worst", "prevented_fraction", "false_activation_rate",
                                          "candidate"], ascending=[False, False, True, True])
    best = int(ranked.index[0])
    table.loc[best, "chosen"] = True
    return candidates[best], table
