"""What the uncertainty estimates know about a collision in the next second beyond the safety rule's proximity terms
(paper eq. (10)), from the perturbation study's per-step records; and the episode-cluster bootstrap behind it.

Question. The safety rule fires when ``(c_ep or c_feat) and c_prox and c_ap``: near a human, approaching, AND
uncertain. The uncertainty gate only matters if the uncertainty tells risky proximity steps from harmless ones. We
measure, per estimator (MC-dropout, ensemble), perturbation type and uncertainty (epistemic / aleatoric heading and
speed, predictive feature; raw ``u_*`` and windowed ``w_u_*``), how well it ranks the steps followed by a collision
within the next second:

- **label**: row ``t`` of an episode that ends in a collision at its last row ``T`` is positive iff
  ``t >= T - (H - 1)``, ``H = 4`` steps (1 s at dt = 0.25 s): the collision happens within ``H`` steps of the
  observation the row's uncertainty was estimated from (the last row's step is the colliding one);
- **proximity state at the decision** (what the rule reads at row ``t``): the recorded ``nearest_gap`` of a row is
  the gap AFTER its step, so ``d(t)`` is the previous row's gap and ``|dv|(t)`` the previous row's
  ``nearest_relative_speed``; ``c_prox = [d + beta1 |dv| < lambda_prox]`` (the paper's ``lambda_prox = 0.9``,
  ``beta1 = 0.5``, ``|dv|`` reading), ``c_ap = [d(t) <= d(t-1)]`` (True when ``d(t-1)`` is unknown, as the rule).
  The first row of an episode has no ``d(t)`` and is left out. These gaps are the simulator's true ones: under
  observation noise the rule's *perceived* proximity terms are noisier than these;
- **metrics**: AUROC = P(score of a positive > score of a negative) + P(tie) / 2 (the Mann-Whitney U / (n1 n0));
  AUPRC = average precision ``sum_k (R_k - R_(k-1)) P_k`` over the distinct scores, highest first (tied scores
  form one threshold); (i) the uncertainty alone over all steps; (ii) the same among the steps where
  ``c_prox and c_ap`` hold (what the uncertainty adds where the rule asks it); (iii) incremental value: a
  logistic model of the proximity state (gap, log gap, ``|dv|``, ``c_ap``, ``c_prox and c_ap``) vs the same plus
  the uncertainty (its quantile), both cross-fitted over 5 folds of episodes; the AUROC difference;
- **intervals**: percentile intervals of a cluster bootstrap over EPISODES (an episode's steps are not
  independent): every resample draws, within each strength, as many episodes as there are, with replacement, and
  weighs each step by its episode's count. The resampled metrics are exact (no re-sorting): per positive step the
  counts of negatives below / tied and of steps at or above its score, per episode, are computed once. Seeded,
  deterministic. The cross-fitted model scores stay fixed in the resamples (the interval does not include the
  models' refitting). Intervals are per test (95 %), not adjusted for the many measures shown.

The same bootstrap of episodes (:func:`cluster_counts`, :func:`percentile_interval`) gives the Table 2 claims'
intervals (`socnav.paper.uncertainty.table2_claims`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import scipy.special
import scipy.stats

from socnav.experiments.registry import ReportContext
from socnav.experiments.statistics import Interval
from socnav.io import save_figure, write_table_atomic, write_text_atomic
from socnav.paper.labels import (
    ESTIMATOR_LABELS,
    ESTIMATOR_ORDER,
    MEASURE_LABELS,
    PERTURBATION_ORDER,
    UNCERTAINTY_LABELS,
)
from socnav.paper.uncertainty.records import read_record_columns, record_files
from socnav.safety.rule import THRESHOLD_PRESETS

__all__ = [
    "DIAGNOSTIC_COLUMNS", "HORIZON_STEPS", "INFORMATION_COLUMNS", "MEASURES", "MEASURE_LABELS", "PROXIMITY_MODEL",
    "PROXIMITY_SCORE", "RULE_MEASURES", "Ranking", "auroc", "average_precision", "bonferroni_confidence",
    "cluster_counts", "collision_soon", "cross_fitted_scores", "fit_logistic", "gate_diagnostics",
    "information_table", "percentile_interval", "plot_information", "prepare_steps", "proximity_features",
    "ranking_draws", "ranking_intervals", "read_study_steps", "study_step_files",
]

HORIZON_STEPS = 4  # 1 s at dt = 0.25 s
LAMBDA_PROX, BETA1 = THRESHOLD_PRESETS["mc"][2:]  # the paper's proximity constants (the same for both estimators)
DEFAULT_RESAMPLES = 1000
DEFAULT_CONFIDENCE = 0.95
N_FOLDS = 5

#: Uncertainty columns measured: raw and windowed (the mean of the last w steps, "w_" prefix).
MEASURES = list(UNCERTAINTY_LABELS) + [f"w_{name}" for name in UNCERTAINTY_LABELS]
PROXIMITY_SCORE = "proximity score"  # -(d + beta1 |dv|): closer and slower ranks higher, as c_prox reads it
PROXIMITY_MODEL = "proximity model"  # the cross-fitted logistic model of the proximity state
STEP_COLUMNS = ["estimator", "perturbation", "strength", "episode", "step", *MEASURES, "nearest_gap",
                "nearest_relative_speed", "outcome"]


# --------------------------------------------------------------------------------------------------------------
# Labels and the proximity state
# --------------------------------------------------------------------------------------------------------------

def collision_soon(episode: np.ndarray, step: np.ndarray, outcome: np.ndarray,
                   horizon: int = HORIZON_STEPS) -> np.ndarray:
    """Per row: its episode ends in a collision within ``horizon`` steps (rows ``T - horizon + 1 ... T``, ``T`` the
    episode's last row, whose step is the colliding one). `episode` may be any hashable key per row."""
    frame = pd.DataFrame({"episode": episode, "step": np.asarray(step), "outcome": outcome})
    grouped = frame.groupby("episode", sort=False)
    last = grouped["step"].transform("max").to_numpy()
    collided = grouped["outcome"].transform(lambda o: (o == "collision").any()).to_numpy(bool)
    return collided & (frame["step"].to_numpy() > last - horizon)


def prepare_steps(steps: pd.DataFrame, horizon: int = HORIZON_STEPS, lambda_prox: float = LAMBDA_PROX,
                  beta1: float = BETA1) -> pd.DataFrame:
    """One (estimator, perturbation)'s per-step records -> the rows the analysis uses, with ``cluster`` (an int id
    of the episode: (strength, episode)), ``label`` (collision within `horizon` steps), the proximity state at the
    decision -- ``gap`` = d(t), ``previous_gap`` = d(t-1) (NaN at the second row), ``relative_speed`` = |dv|(t),
    ``score`` = d + beta1 |dv|, ``c_prox``, ``c_ap``, ``proximity`` = c_prox and c_ap -- and ``stratum`` (the
    strength's index). The first row of each episode (no d(t)) is dropped."""
    frame = steps.sort_values(["strength", "episode", "step"], kind="stable", ignore_index=True)
    cluster = frame.groupby(["strength", "episode"], sort=True).ngroup().to_numpy()
    frame = frame.assign(cluster=cluster)
    frame["label"] = collision_soon(cluster, frame["step"].to_numpy(), frame["outcome"].to_numpy(), horizon)
    by_episode = frame.groupby("cluster", sort=False)
    frame["gap"] = by_episode["nearest_gap"].shift(1).astype(float)
    frame["previous_gap"] = by_episode["nearest_gap"].shift(2).astype(float)
    frame["relative_speed"] = by_episode["nearest_relative_speed"].shift(1).astype(float)
    frame = frame[frame["gap"].notna()].reset_index(drop=True)
    gap = frame["gap"].to_numpy(float)
    frame["score"] = gap + beta1 * np.abs(frame["relative_speed"].to_numpy(float))
    frame["c_prox"] = np.isfinite(gap) & (frame["score"].to_numpy() < lambda_prox)
    previous = frame["previous_gap"].to_numpy(float)
    frame["c_ap"] = np.isnan(previous) | (gap <= previous)
    frame["proximity"] = frame["c_prox"] & frame["c_ap"]
    strengths = np.sort(frame["strength"].unique())
    frame["stratum"] = np.searchsorted(strengths, frame["strength"].to_numpy())
    return frame


# --------------------------------------------------------------------------------------------------------------
# Ranking metrics, exact under episode weights
# --------------------------------------------------------------------------------------------------------------

def auroc(scores: Any, labels: Any) -> float:
    """Area under the ROC curve: ``(R_pos - n1 (n1 + 1) / 2) / (n1 n0)`` with ``R_pos`` the sum of the positives'
    mid-ranks (= P(positive > negative) + P(tie) / 2). NaN without positives or negatives."""
    scores, labels = np.asarray(scores, dtype=float), np.asarray(labels, dtype=bool)
    n1, n0 = int(labels.sum()), int((~labels).sum())
    if n1 == 0 or n0 == 0:
        return math.nan
    ranks = scipy.stats.rankdata(scores)  # ties get their mid-rank
    return float((ranks[labels].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def average_precision(scores: Any, labels: Any) -> float:
    """Area under the precision-recall curve as average precision: ``sum_k (R_k - R_(k-1)) P_k`` over the distinct
    scores ``t_k`` from the highest, ``P_k`` / ``R_k`` the precision / recall of "score >= t_k". NaN without
    positives."""
    scores, labels = np.asarray(scores, dtype=float), np.asarray(labels, dtype=bool)
    n1 = int(labels.sum())
    if n1 == 0:
        return math.nan
    thresholds, inverse = np.unique(-scores, return_inverse=True)  # ascending -score: highest score first
    positives = np.bincount(inverse, weights=labels, minlength=len(thresholds))
    totals = np.bincount(inverse, minlength=len(thresholds))
    true_positives, selected = np.cumsum(positives), np.cumsum(totals)
    return float(np.sum(positives / n1 * true_positives / selected))


def cluster_counts(strata: Any, n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> np.ndarray:
    """Cluster (episode) bootstrap: ``(n_resamples, n_clusters)`` counts, how often each cluster is drawn. Cluster
    ``j`` belongs to stratum ``strata[j]``; within each stratum as many clusters are drawn, with replacement, as it
    has, so every resample keeps the strata's sizes. Seeded and deterministic."""
    strata = np.asarray(strata)
    rng = np.random.default_rng(seed)
    counts = np.zeros((n_resamples, len(strata)), dtype=np.int64)
    rows = np.arange(n_resamples)[:, None]
    for stratum in np.unique(strata):  # sorted: the draws do not depend on the order of the clusters' strata
        members = np.flatnonzero(strata == stratum)
        drawn = members[rng.integers(0, len(members), size=(n_resamples, len(members)))]
        np.add.at(counts, (np.broadcast_to(rows, drawn.shape), drawn), 1)
    return counts


def ranking_draws(scores: Any, labels: Any, clusters: Any, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """AUROC and average precision of `scores` for each row of `counts` (``(B, n_clusters)``: every step weighted by
    its cluster's count), exactly as :func:`auroc` / :func:`average_precision` on the data with each cluster
    repeated that often; NaN where a resample has no positive or no negative step.

    Per positive step ``i`` and cluster ``f`` we count once the negatives of ``f`` below ``s_i`` (ties: half), and
    the positives / negatives of ``f`` at or above ``s_i``; a resample with counts ``c`` then has
    ``AUROC = sum_i c_e(i) (c . below_i) / (P N)`` and ``AP = sum_i c_e(i) TP_i / (TP_i + FP_i) / P``,
    ``TP_i = c . pos_ge_i``, ``FP_i = c . neg_ge_i``, ``P`` / ``N`` the weighted numbers of positives / negatives.
    """
    scores, labels = np.asarray(scores, dtype=float), np.asarray(labels, dtype=bool)
    clusters = np.asarray(clusters, dtype=np.int64)
    counts = np.atleast_2d(np.asarray(counts, dtype=float))
    n_clusters = counts.shape[1]
    nan = np.full(len(counts), np.nan)
    if not labels.any() or labels.all():
        return nan, nan.copy()
    positive_scores, positive_clusters = scores[labels], clusters[labels]
    below = np.zeros((len(positive_scores), n_clusters))
    negatives_at_or_above = np.zeros_like(below)
    positives_at_or_above = np.zeros_like(below)
    order = np.lexsort((scores, clusters))  # by cluster, then score
    sorted_scores, sorted_clusters, sorted_labels = scores[order], clusters[order], labels[order]
    bounds = np.searchsorted(sorted_clusters, np.arange(n_clusters + 1))
    for f in range(n_clusters):
        segment = slice(bounds[f], bounds[f + 1])
        if bounds[f] == bounds[f + 1]:
            continue
        values, is_positive = sorted_scores[segment], sorted_labels[segment]
        negatives, positives = values[~is_positive], values[is_positive]  # each still sorted
        if len(negatives):
            low = np.searchsorted(negatives, positive_scores, "left")
            high = np.searchsorted(negatives, positive_scores, "right")
            below[:, f] = low + 0.5 * (high - low)
            negatives_at_or_above[:, f] = len(negatives) - low
        if len(positives):
            positives_at_or_above[:, f] = len(positives) - np.searchsorted(positives, positive_scores, "left")
    n_positive = np.bincount(clusters[labels], minlength=n_clusters)
    n_negative = np.bincount(clusters[~labels], minlength=n_clusters)
    weighted_positives, weighted_negatives = counts @ n_positive, counts @ n_negative
    weight = counts[:, positive_clusters]  # (B, n_pos): the count of each positive step's episode
    with np.errstate(invalid="ignore", divide="ignore"):
        area = (weight * (counts @ below.T)).sum(axis=1) / (weighted_positives * weighted_negatives)
        true_positives = counts @ positives_at_or_above.T
        selected = true_positives + counts @ negatives_at_or_above.T
        precision = np.divide(true_positives, selected, out=np.zeros_like(selected), where=weight > 0)
        ap = (weight * precision).sum(axis=1) / weighted_positives
    defined = (weighted_positives > 0) & (weighted_negatives > 0)
    return np.where(defined, area, np.nan), np.where(weighted_positives > 0, ap, np.nan)


def percentile_interval(estimate: float, draws: Any, confidence: float = DEFAULT_CONFIDENCE,
                        min_defined: float = 0.9) -> Interval:
    """Percentile bootstrap interval of `estimate` from its resampled `draws`; NaN bounds when the estimate is NaN
    or fewer than `min_defined` of the draws are defined (e.g. resamples without a collision)."""
    draws = np.asarray(draws, dtype=float)
    finite = draws[np.isfinite(draws)]
    if not math.isfinite(estimate) or len(finite) < max(2, min_defined * len(draws)):
        return Interval(float(estimate), math.nan, math.nan)
    alpha = 1.0 - confidence
    low, high = np.quantile(finite, [alpha / 2, 1 - alpha / 2])
    return Interval(float(estimate), float(low), float(high))


def bonferroni_confidence(confidence: float, tests: int) -> float:
    """The per-test confidence level that keeps the family-wise coverage of `tests` intervals at `confidence`."""
    return 1.0 - (1.0 - confidence) / max(1, tests)


@dataclass(frozen=True)
class Ranking:
    """AUROC and AUPRC with their intervals, on ``steps`` steps (``positives`` of them labelled) of ``episodes``."""

    auroc: Interval
    auprc: Interval
    steps: int
    positives: int
    episodes: int


def ranking_intervals(scores: Any, labels: Any, clusters: Any, counts: np.ndarray,
                      confidence: float = DEFAULT_CONFIDENCE) -> tuple[Ranking, np.ndarray]:
    """AUROC / AUPRC of `scores` with cluster-bootstrap intervals (`counts` from :func:`cluster_counts`); also
    returns the resampled AUROCs (for differences between scores under the same resamples)."""
    labels = np.asarray(labels, dtype=bool)
    clusters = np.asarray(clusters)
    ones = np.ones((1, counts.shape[1]))
    point_auroc, point_ap = ranking_draws(scores, labels, clusters, ones)
    auroc_draws, ap_draws = ranking_draws(scores, labels, clusters, counts)
    ranking = Ranking(percentile_interval(float(point_auroc[0]), auroc_draws, confidence),
                      percentile_interval(float(point_ap[0]), ap_draws, confidence),
                      steps=len(labels), positives=int(labels.sum()), episodes=len(np.unique(clusters)))
    return ranking, auroc_draws


# --------------------------------------------------------------------------------------------------------------
# The proximity-only model and the model with the uncertainty
# --------------------------------------------------------------------------------------------------------------

def proximity_features(frame: pd.DataFrame) -> np.ndarray:
    """The proximity state at the decision as model inputs: ``min(d, 5)``, ``log(clip(d, 0, 5) + 0.05)``,
    ``min(|dv|, 5)``, ``c_ap``, ``c_prox and c_ap`` (``d = inf`` without a human reads as 5 m)."""
    gap = np.clip(frame["gap"].to_numpy(float), 0.0, 5.0)
    speed = np.minimum(np.abs(frame["relative_speed"].to_numpy(float)), 5.0)
    return np.column_stack([gap, np.log(gap + 0.05), speed, frame["c_ap"].to_numpy(float),
                            frame["proximity"].to_numpy(float)])


def fit_logistic(features: np.ndarray, labels: np.ndarray, l2: float = 1e-3, iterations: int = 50) -> np.ndarray:
    """Logistic regression ``P(y = 1) = sigmoid(w0 + x . w)`` minimising the mean log loss plus ``l2 / 2 |w|^2``
    (not on the intercept; it keeps separable data finite) by Newton's method::

        g = X^T (sigmoid(X w) - y) / n + L w,   H = X^T diag(p (1 - p)) X / n + L,   w <- w - H^-1 g

    Returns ``(w0, w...)``."""
    x = np.column_stack([np.ones(len(features)), features])
    y = np.asarray(labels, dtype=float)
    penalty = np.diag(np.r_[1e-10, np.full(features.shape[1], l2)])
    w = np.zeros(x.shape[1])
    for _ in range(iterations):
        p = scipy.special.expit(x @ w)
        gradient = x.T @ (p - y) / len(y) + penalty @ w
        hessian = (x * (p * (1 - p))[:, None]).T @ x / len(y) + penalty
        step = np.linalg.solve(hessian, gradient)
        w -= step
        if np.max(np.abs(step)) < 1e-9:
            break
    return w


def cross_fitted_scores(features: np.ndarray, labels: Any, clusters: Any, n_folds: int = N_FOLDS,
                        seed: int = 0) -> np.ndarray:
    """Out-of-fold linear predictor of :func:`fit_logistic`: the episodes are split into `n_folds` folds (seeded
    permutation), each fold scored by the model fitted on the others (inputs standardised with the training folds'
    mean and std). A training set without a positive scores its fold 0."""
    labels, clusters = np.asarray(labels, dtype=bool), np.asarray(clusters)
    unique = np.unique(clusters)
    fold_of = dict(zip(unique, np.random.default_rng(seed).permutation(len(unique)) % n_folds, strict=True))
    fold = np.array([fold_of[c] for c in clusters])
    scores = np.zeros(len(labels))
    for k in range(n_folds):
        train, test = fold != k, fold == k
        if not test.any() or not labels[train].any() or labels[train].all():
            continue
        mean, std = features[train].mean(axis=0), features[train].std(axis=0)
        std = np.where(std > 0, std, 1.0)
        w = fit_logistic((features[train] - mean) / std, labels[train])
        scores[test] = w[0] + ((features[test] - mean) / std) @ w[1:]
    return scores


# --------------------------------------------------------------------------------------------------------------
# The table
# --------------------------------------------------------------------------------------------------------------

INFORMATION_COLUMNS = [
    "estimator", "perturbation", "scope", "measure", "episodes", "collision_episodes", "steps", "positives",
    "auroc", "auroc_low", "auroc_high", "auprc", "auprc_low", "auprc_high", "base_rate",
    "proximity_steps", "proximity_positives", "proximity_base_rate", "proximity_auroc", "proximity_auroc_low",
    "proximity_auroc_high", "proximity_auprc", "proximity_auprc_low", "proximity_auprc_high",
    "model_auroc", "combined_auroc", "delta_auroc", "delta_auroc_low", "delta_auroc_high",
]


def _cell_rows(frame: pd.DataFrame, measures: Sequence[str], n_resamples: int, seed: int, confidence: float,
               incremental: bool) -> list[dict[str, Any]]:
    """The rows of one (estimator, perturbation, scope): every measure, the proximity score and (with
    `incremental`) the proximity model, alone, within proximity and (measures) added to the proximity model."""
    labels, clusters = frame["label"].to_numpy(bool), frame["cluster"].to_numpy()
    # clusters renumbered 0..E-1 within this scope; strata: the strength of each cluster
    ids, clusters = np.unique(clusters, return_inverse=True)
    strata = frame.groupby(clusters)["stratum"].first().to_numpy()
    counts = cluster_counts(strata, n_resamples, seed)
    near = frame["proximity"].to_numpy(bool)
    common = {"episodes": len(ids), "collision_episodes": int(frame.loc[labels, "cluster"].nunique()),
              "steps": len(frame), "positives": int(labels.sum()), "base_rate": float(labels.mean()),
              "proximity_steps": int(near.sum()), "proximity_positives": int(labels[near].sum()),
              "proximity_base_rate": float(labels[near].mean()) if near.any() else math.nan}
    model_scores = model_draws = None
    if incremental:
        proximity = proximity_features(frame)
        model_scores = cross_fitted_scores(proximity, labels, clusters, seed=seed)
    candidates: dict[str, np.ndarray] = {m: frame[m].to_numpy(float) for m in measures if m in frame}
    candidates[PROXIMITY_SCORE] = -frame["score"].to_numpy(float)
    if model_scores is not None:
        candidates[PROXIMITY_MODEL] = model_scores
    rows: list[dict[str, Any]] = []
    for name, scores in candidates.items():
        alone, draws = ranking_intervals(scores, labels, clusters, counts, confidence)
        within, _ = ranking_intervals(scores[near], labels[near], clusters[near], counts, confidence)
        row = {**common, "measure": name,
               **_interval_columns("auroc", alone.auroc), **_interval_columns("auprc", alone.auprc),
               **_interval_columns("proximity_auroc", within.auroc),
               **_interval_columns("proximity_auprc", within.auprc)}
        if name == PROXIMITY_MODEL:
            model_draws = draws
        if model_scores is not None and name not in (PROXIMITY_SCORE, PROXIMITY_MODEL):
            quantile = scipy.stats.rankdata(scores) / len(scores)  # the uncertainty as a model input: its quantile
            combined = cross_fitted_scores(np.column_stack([proximity, quantile]), labels, clusters, seed=seed)
            with_uncertainty, combined_draws = ranking_intervals(combined, labels, clusters, counts, confidence)
            row["combined_auroc"] = with_uncertainty.auroc.estimate
            row["_combined"] = combined_draws
        rows.append(row)
    model = next((r for r in rows if r["measure"] == PROXIMITY_MODEL), None)
    for row in rows:
        row["model_auroc"] = model["auroc"] if model is not None else math.nan
        row_draws = row.pop("_combined", None)
        if row_draws is not None and model is not None and model_draws is not None:
            # the same resamples for both scores: the difference's draws are paired
            delta = percentile_interval(row["combined_auroc"] - model["auroc"], row_draws - model_draws, confidence)
            row.update(_interval_columns("delta_auroc", delta))
    return rows


def _interval_columns(name: str, interval: Interval) -> dict[str, float]:
    return {name: interval.estimate, f"{name}_low": interval.low, f"{name}_high": interval.high}


def information_table(steps: pd.DataFrame, measures: Sequence[str] = MEASURES,
                      n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, confidence: float = DEFAULT_CONFIDENCE,
                      horizon: int = HORIZON_STEPS, incremental: bool = True) -> pd.DataFrame:
    """Per (estimator, perturbation) of the study's per-step records and scope -- ``all`` strengths pooled, the
    ``largest`` strength alone -- one row per measure (every uncertainty column present, the proximity score and
    the proximity model) with AUROC / AUPRC alone and among the proximity-firing steps, and (scope ``all``, with
    `incremental`) the AUROC of the proximity model, of the model plus the measure and their difference; each with
    its cluster-bootstrap interval over episodes (columns ``*_low`` / ``*_high``)."""
    rows = []
    for (estimator, perturbation), group in steps.groupby(["estimator", "perturbation"], sort=False):
        frame = prepare_steps(group, horizon)
        largest = frame["strength"].max()
        for scope, chosen in (("all", frame), ("largest", frame[frame["strength"] == largest])):
            if chosen.empty:
                continue
            cell = _cell_rows(chosen.reset_index(drop=True), measures, n_resamples, seed, confidence,
                              incremental and scope == "all")
            rows += [{"estimator": estimator, "perturbation": perturbation, "scope": scope, **row} for row in cell]
    return pd.DataFrame(rows, columns=INFORMATION_COLUMNS)


# --------------------------------------------------------------------------------------------------------------
# Why: what the gate sees where the proximity terms fire
# --------------------------------------------------------------------------------------------------------------

DIAGNOSTIC_COLUMNS = [
    "estimator", "perturbation", "steps", "proximity_steps", "lambda_ep", "lambda_feat", "gate_open_pct",
    "c_ep_pct", "c_feat_pct", "gate_open_pct_all_steps", "c_ep_pct_all_steps", "c_feat_pct_all_steps",
    "w_u_ep_heading_p05_proximity", "w_u_ep_heading_median_proximity", "w_u_feat_p05_proximity",
    "w_u_feat_median_proximity", "w_u_feat_max", "spearman_w_u_ep_heading_gap", "spearman_w_u_feat_gap",
    "collisions", "collisions_proximity_fired_pct", "collisions_rule_fired_pct",
]


def gate_diagnostics(steps: pd.DataFrame, thresholds: dict[str, tuple[float, float]] | None = None,
                     horizon: int = HORIZON_STEPS) -> pd.DataFrame:
    """Per (estimator, perturbation), all strengths pooled: how often the uncertainty gate ``c_ep or c_feat``
    (windowed values, the paper's thresholds of that estimator unless `thresholds` maps estimator -> (lambda_ep,
    lambda_feat)) is already open where the proximity terms fire (100 %: the gate can never veto) and at all steps;
    quantiles of the windowed values there; their Spearman correlation with the gap d(t) (negative: higher when a
    human is near); and the share of collision episodes where the proximity terms / the whole rule fired on at
    least one of the last `horizon` rows (the rule's chance to act)."""
    rows = []
    for (estimator, perturbation), group in steps.groupby(["estimator", "perturbation"], sort=False):
        frame = prepare_steps(group, horizon)
        preset = (thresholds or {}).get(estimator) or THRESHOLD_PRESETS.get(estimator, (math.inf, math.inf))[:2]
        lambda_ep, lambda_feat = preset
        ep = frame["w_u_ep_heading"].to_numpy(float)
        feat = frame["w_u_feat"].to_numpy(float)
        c_ep, c_feat = ep > lambda_ep, feat > lambda_feat
        gate = c_ep | c_feat
        near = frame["proximity"].to_numpy(bool)
        finite = np.isfinite(frame["gap"].to_numpy(float))
        labels = frame["label"].to_numpy(bool)
        fired = pd.DataFrame({"cluster": frame["cluster"], "near": near & labels, "rule": near & gate & labels})
        last = fired[labels].groupby("cluster")[["near", "rule"]].any()
        rows.append({
            "estimator": estimator, "perturbation": perturbation, "steps": len(frame),
            "proximity_steps": int(near.sum()),
            "lambda_ep": lambda_ep, "lambda_feat": lambda_feat,
            "gate_open_pct": _pct(gate[near]), "c_ep_pct": _pct(c_ep[near]), "c_feat_pct": _pct(c_feat[near]),
            "gate_open_pct_all_steps": _pct(gate), "c_ep_pct_all_steps": _pct(c_ep),
            "c_feat_pct_all_steps": _pct(c_feat),
            "w_u_ep_heading_p05_proximity": _quantile(ep[near], 0.05),
            "w_u_ep_heading_median_proximity": _quantile(ep[near], 0.5),
            "w_u_feat_p05_proximity": _quantile(feat[near], 0.05),
            "w_u_feat_median_proximity": _quantile(feat[near], 0.5), "w_u_feat_max": float(np.max(feat)),
            "spearman_w_u_ep_heading_gap": _spearman(ep[finite], frame["gap"].to_numpy(float)[finite]),
            "spearman_w_u_feat_gap": _spearman(feat[finite], frame["gap"].to_numpy(float)[finite]),
            "collisions": len(last), "collisions_proximity_fired_pct": _pct(last["near"].to_numpy(bool)),
            "collisions_rule_fired_pct": _pct(last["rule"].to_numpy(bool)),
        })
    return pd.DataFrame(rows, columns=DIAGNOSTIC_COLUMNS)


def _pct(mask: np.ndarray) -> float:
    return 100.0 * float(np.mean(mask)) if len(mask) else math.nan


def _quantile(values: np.ndarray, q: float) -> float:
    return float(np.quantile(values, q)) if len(values) else math.nan


def _spearman(x: np.ndarray, y: np.ndarray) -> float:
    if len(x) < 3 or np.all(x == x[0]) or np.all(y == y[0]):
        return math.nan
    return float(scipy.stats.spearmanr(x, y).statistic)


# --------------------------------------------------------------------------------------------------------------
# Report section
# --------------------------------------------------------------------------------------------------------------

RULE_MEASURES = ["w_u_ep_heading", "w_u_feat"]  # what the rule's gate reads


def study_step_files(context: ReportContext) -> list[Path]:
    """The study's ``steps.parquet`` files, without those inside a planned unit that is not (yet) done."""
    return record_files(context, "study/*/*/steps.parquet")


def read_study_steps(paths: Iterable[Path], columns: Sequence[str] = STEP_COLUMNS) -> pd.DataFrame:
    """The wanted columns of study step files (``study/<estimator>/<perturbation>/steps.parquet``)."""
    frames = [read_record_columns(path, columns) for path in paths]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=list(columns))


def _in_report_order(steps: pd.DataFrame) -> pd.DataFrame:
    """The records ordered MC-dropout first, then the ensemble, perturbation types in their usual order."""
    rank = {name: i for i, name in enumerate([*ESTIMATOR_ORDER, *PERTURBATION_ORDER])}
    keys = steps[["estimator", "perturbation"]].apply(lambda column: column.map(rank).fillna(len(rank)))
    order = np.lexsort((keys["perturbation"].to_numpy(), keys["estimator"].to_numpy()))
    return steps.iloc[order].reset_index(drop=True)


def _number(value: float, spec: str) -> str:
    return format(value, spec) if math.isfinite(value) else "–"


def _ci(row: Any, name: str, decimals: int = 2) -> str:
    return Interval(row[name], row[f"{name}_low"], row[f"{name}_high"]).text(decimals)


def information_markdown(table: pd.DataFrame) -> str:
    """The rule's inputs (windowed epistemic heading, windowed feature) and the proximity references, all strengths
    pooled: AUROC alone, AUROC / AUPRC among proximity-firing steps, AUROC gain over the proximity model."""
    header = ["Estimator", "Perturbation", "Score", "AUROC alone", "AUPRC alone (base rate)",
              "AUROC given proximity (steps, positives)", "AUPRC given proximity (base rate)",
              "ΔAUROC over proximity model"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--"] * 3 + ["--:"] * 5) + "|"]
    chosen = table[(table["scope"] == "all")
                   & table["measure"].isin([*RULE_MEASURES, PROXIMITY_SCORE, PROXIMITY_MODEL])]
    for row in chosen.to_dict("records"):
        delta = _ci(row, "delta_auroc", 3) if math.isfinite(row["delta_auroc"]) else "–"
        lines.append("| " + " | ".join([
            ESTIMATOR_LABELS.get(row["estimator"], row["estimator"]), row["perturbation"].replace("_", " "),
            MEASURE_LABELS.get(row["measure"], row["measure"]), _ci(row, "auroc"),
            f"{_ci(row, 'auprc', 3)} ({_number(row['base_rate'], '.3f')})",
            f"{_ci(row, 'proximity_auroc')} ({row['proximity_steps']}, {row['proximity_positives']})",
            f"{_ci(row, 'proximity_auprc', 3)} ({_number(row['proximity_base_rate'], '.3f')})", delta]) + " |")
    return "\n".join(lines)


def _incremental_summary(table: pd.DataFrame) -> str:
    rows = table[(table["scope"] == "all") & table["measure"].isin(MEASURES) & table["delta_auroc"].notna()]
    if rows.empty:
        return ""
    above = int((rows["delta_auroc_low"] > 0).sum())
    below = int((rows["delta_auroc_high"] < 0).sum())
    within = rows[rows["proximity_auroc"].notna()]
    informative = int((within["proximity_auroc_low"] > 0.5).sum())
    best = rows.loc[rows["delta_auroc"].idxmax()]
    return (f"Over {len(rows)} (estimator, perturbation, uncertainty) combinations, all strengths pooled: adding the "
            f"uncertainty to the proximity model raises the AUROC with an interval above 0 in {above}, lowers it "
            f"(interval below 0) in {below}, and cannot tell in {len(rows) - above - below}; the median change is "
            f"{rows['delta_auroc'].median():+.4f} and the largest gain "
            f"{best['delta_auroc']:+.3f} ({MEASURE_LABELS.get(best['measure'], best['measure'])}, "
            f"{ESTIMATOR_LABELS.get(best['estimator'], best['estimator'])}, {best['perturbation'].replace('_', ' ')}). "
            f"Among the proximity-firing steps the uncertainty ranks better than chance (AUROC interval above 0.5) "
            f"in {informative} of {len(within)}. Intervals are per test (95 %), not adjusted for the number shown.")


def diagnostics_markdown(diagnostics: pd.DataFrame) -> str:
    """The gate diagnostics (:func:`gate_diagnostics`) as a Markdown table, one row per estimator and perturbation."""
    header = ["Estimator", "Perturbation", "Proximity-firing steps", "Gate open there % (c_ep / c_feat)",
              "Gate open, all steps %", "w_u_ep_heading p5 / median there (λ_ep)",
              "w_u_feat p5 / median there (λ_f)", "Spearman with gap (ep / feat)",
              "Collisions: proximity fired / rule fired in last 1 s %"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--"] * 2 + ["--:"] * 7) + "|"]
    for row in diagnostics.to_dict("records"):
        lines.append("| " + " | ".join([
            ESTIMATOR_LABELS.get(row["estimator"], row["estimator"]), row["perturbation"].replace("_", " "),
            f"{row['proximity_steps']} of {row['steps']}",
            f"{_number(row['gate_open_pct'], '.1f')} ({_number(row['c_ep_pct'], '.1f')} / "
            f"{_number(row['c_feat_pct'], '.1f')})",
            _number(row["gate_open_pct_all_steps"], ".1f"),
            f"{_number(row['w_u_ep_heading_p05_proximity'], '.3g')} / "
            f"{_number(row['w_u_ep_heading_median_proximity'], '.3g')} ({row['lambda_ep']:g})",
            f"{_number(row['w_u_feat_p05_proximity'], '.3g')} / "
            f"{_number(row['w_u_feat_median_proximity'], '.3g')} ({row['lambda_feat']:g})",
            f"{_number(row['spearman_w_u_ep_heading_gap'], '+.2f')} / "
            f"{_number(row['spearman_w_u_feat_gap'], '+.2f')}",
            f"{_number(row['collisions_proximity_fired_pct'], '.0f')} / "
            f"{_number(row['collisions_rule_fired_pct'], '.0f')} (of {row['collisions']})"]) + " |")
    return "\n".join(lines)


def plot_information(table: pd.DataFrame, out_base: Path) -> list[Path]:
    """One panel per estimator: per perturbation type (all strengths pooled) the AUROC (with interval) of the
    proximity score, and of the rule's two windowed uncertainties alone and among proximity-firing steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pooled = table[table["scope"] == "all"]
    estimators = list(dict.fromkeys(pooled["estimator"]))
    perturbations = list(dict.fromkeys(pooled["perturbation"]))
    series = [(PROXIMITY_SCORE, "auroc", "proximity score, all steps", "0.4", "o"),
              (PROXIMITY_SCORE, "proximity_auroc", "proximity score, proximity firing", "0.4", "^"),
              ("w_u_ep_heading", "auroc", "w_u_ep_heading, all steps", "tab:blue", "o"),
              ("w_u_ep_heading", "proximity_auroc", "w_u_ep_heading, proximity firing", "tab:blue", "^"),
              ("w_u_feat", "auroc", "w_u_feat, all steps", "tab:red", "o"),
              ("w_u_feat", "proximity_auroc", "w_u_feat, proximity firing", "tab:red", "^")]
    figure, axes = plt.subplots(1, len(estimators), figsize=(1.6 + 1.4 * len(perturbations) * len(estimators), 4.6),
                                squeeze=False)
    for axis, estimator in zip(axes[0], estimators, strict=True):
        rows = pooled[pooled["estimator"] == estimator].set_index(["perturbation", "measure"])
        for offset, (measure, column, label, colour, marker) in enumerate(series):
            x, y, low, high = [], [], [], []
            for index, perturbation in enumerate(perturbations):
                if (perturbation, measure) not in rows.index:
                    continue
                row = rows.loc[(perturbation, measure)]
                x.append(index + 0.11 * (offset - 2.5))
                y.append(row[column])
                low.append(row[column] - row[f"{column}_low"])
                high.append(row[f"{column}_high"] - row[column])
            errors = np.nan_to_num(np.array([low, high], dtype=float))
            axis.errorbar(x, y, yerr=errors, linestyle="none", marker=marker, color=colour, label=label,
                          markersize=4, capsize=2, markerfacecolor="white" if marker == "^" else colour)
        axis.axhline(0.5, color="0.7", linewidth=0.8, linestyle="--")
        axis.set_xticks(range(len(perturbations)))
        axis.set_xticklabels([p.replace("_", "\n") for p in perturbations], fontsize=8)
        axis.set_ylim(0, 1)
        axis.set_ylabel("AUROC, collision within 1 s")
        axis.set_title(ESTIMATOR_LABELS.get(estimator, estimator))
        axis.grid(alpha=0.3, axis="y")
    handles, labels = axes[0][0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    figure.tight_layout(rect=(0, 0.13, 1, 1))
    return save_figure(figure, out_base)


def uncertainty_information_section(context: ReportContext) -> str:
    """The section: uncertainty_information.md/csv/png/svg and the gate diagnostics (empty without step records)."""
    steps = read_study_steps(study_step_files(context))
    if steps.empty or not {"nearest_gap", "nearest_relative_speed", "outcome"} <= set(steps.columns):
        return ""
    steps = _in_report_order(steps)
    table = information_table(steps)
    diagnostics = gate_diagnostics(steps)
    write_table_atomic(table, context.out_dir / "uncertainty_information.csv")
    write_table_atomic(diagnostics, context.out_dir / "uncertainty_information_gate.csv")
    plot_information(table, context.out_dir / "uncertainty_information")
    markdown = information_markdown(table)
    write_text_atomic(context.out_dir / "uncertainty_information.md",
                      markdown + "\n\n" + diagnostics_markdown(diagnostics) + "\n")
    lines = [
        "## What the uncertainty knows about a collision in the next second",
        "",
        f"Label: the step's episode ends in a collision within {HORIZON_STEPS} steps (1 s) of the observation the "
        "uncertainty was estimated from. Proximity terms at the decision as the safety rule reads them (paper eq. "
        f"(10)): c_prox = [d + {BETA1:g}·|Δv| < {LAMBDA_PROX:g}] and c_ap = [d(t) ≤ d(t−1)], d the true gap to "
        "the nearest human (the rule reads the observed one, noisier under observation noise). AUROC alone: over "
        "all steps; given proximity: among the steps where c_prox and c_ap hold (number of steps and positives "
        "in brackets); ΔAUROC: a logistic model of the proximity state plus the uncertainty vs the proximity state "
        "alone, both cross-fitted over episodes. All strengths of a perturbation pooled; [95 % interval] from a "
        "bootstrap over episodes (within each strength). The proximity score ranks by −(d + β1·|Δv|); the "
        "proximity model is the cross-fitted model without uncertainty.",
        "",
        markdown,
        "",
    ]
    summary = _incremental_summary(table)
    if summary:
        lines += [summary, ""]
    lines += [
        "Can the uncertainty gate change a decision at all? Where the proximity terms fire, the share of steps "
        "whose windowed uncertainty already passes the paper's thresholds (c_ep or c_feat; 100 %: the uncertainty "
        "condition can never veto), the windowed values there against the thresholds, their rank correlation with "
        "the gap, and in how many collisions the proximity terms / the whole rule fired at all in the last second:",
        "",
        diagnostics_markdown(diagnostics),
        "",
        "![uncertainty information](uncertainty_information.png)",
        "",
        "Data: [uncertainty_information.csv](uncertainty_information.csv) (every raw and windowed uncertainty, "
        "both scopes: all strengths and the largest strength), "
        "[uncertainty_information_gate.csv](uncertainty_information_gate.csv); "
        "`python docs/analysis/uncertainty_information.py RUN_DIR` prints the diagnostics and can re-estimate "
        "with another p_test or window.",
    ]
    return "\n".join(lines)
