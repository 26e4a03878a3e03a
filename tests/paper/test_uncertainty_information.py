"""What the uncertainty knows (socnav.paper.uncertainty.information) and the Table 2 claims with intervals:
ranking metrics against hand values and brute force, the 1-s label, the proximity state, the episode bootstrap."""

from __future__ import annotations

import itertools

import numpy as np
import pandas as pd
import pytest
import scipy.stats

from socnav.experiments.statistics import CANNOT_TELL, DOES_NOT_HOLD, HOLDS
from socnav.paper.uncertainty.information import (
    auroc,
    average_precision,
    bonferroni_confidence,
    cluster_counts,
    collision_soon,
    cross_fitted_scores,
    fit_logistic,
    gate_diagnostics,
    information_table,
    percentile_interval,
    prepare_steps,
    ranking_draws,
)
from socnav.paper.uncertainty.table2_claims import (
    CLAIM_HEADING_RISES,
    CLAIM_MC_STRONGER,
    CLAIM_MORE_HUMANS,
    claims_summary,
    heading_vs_speed_frame,
    mc_vs_ensemble_frame,
    more_humans_frame,
)

# ------------------------------------------------------------------------------------------------ ranking metrics

def _pairs_auroc(scores, labels):
    """Reference: count every (positive, negative) pair, ties as one half."""
    positives = [s for s, y in zip(scores, labels, strict=True) if y]
    negatives = [s for s, y in zip(scores, labels, strict=True) if not y]
    wins = sum((p > n) + 0.5 * (p == n) for p, n in itertools.product(positives, negatives))
    return wins / (len(positives) * len(negatives))


def _loop_average_precision(scores, labels):
    """Reference: walk the distinct thresholds from the highest, add recall gain x precision."""
    scores, labels = np.asarray(scores, float), np.asarray(labels, bool)
    total, previous_recall = 0.0, 0.0
    for threshold in sorted(set(scores), reverse=True):
        chosen = scores >= threshold
        precision = labels[chosen].sum() / chosen.sum()
        recall = labels[chosen].sum() / labels.sum()
        total += (recall - previous_recall) * precision
        previous_recall = recall
    return total


def test_auroc_hand_values_pair_counting_and_mann_whitney():
    # pos 0.9 beats both negatives, pos 0.7 beats 0.6 only: 3 of 4 pairs
    assert auroc([0.9, 0.8, 0.7, 0.6], [1, 0, 1, 0]) == pytest.approx(0.75)
    # tie: (0.5 pos, 0.5 neg) counts one half, (0.2 pos, 0.5 neg) zero: 0.5 / 2
    assert auroc([0.5, 0.5, 0.2], [1, 0, 1]) == pytest.approx(0.25)
    assert auroc([1.0, 2.0], [0, 1]) == 1.0 and auroc([1.0, 2.0], [1, 0]) == 0.0
    assert np.isnan(auroc([1.0, 2.0], [0, 0])) and np.isnan(auroc([1.0, 2.0], [1, 1]))
    rng = np.random.default_rng(0)
    for _ in range(20):
        scores = rng.integers(0, 5, 30).astype(float)  # many ties
        labels = rng.random(30) < 0.4
        expected = _pairs_auroc(scores, labels)
        assert auroc(scores, labels) == pytest.approx(expected)
        u = scipy.stats.mannwhitneyu(scores[labels], scores[~labels]).statistic
        assert auroc(scores, labels) == pytest.approx(u / (labels.sum() * (~labels).sum()))


def test_average_precision_hand_values_and_reference():
    # thresholds 0.9 (P 1, R 1/2) and 0.7 (P 2/3, R 1): 0.5 * 1 + 0.5 * 2/3
    assert average_precision([0.9, 0.8, 0.7, 0.6], [1, 0, 1, 0]) == pytest.approx(0.5 + 1 / 3)
    # tied 0.5s form one threshold (P 1/2, R 1/2), then 0.2 (P 2/3, R 1): 0.25 + 1/3
    assert average_precision([0.5, 0.5, 0.2], [1, 0, 1]) == pytest.approx(0.25 + 1 / 3)
    assert average_precision([3.0, 2.0, 1.0], [1, 1, 0]) == 1.0
    assert np.isnan(average_precision([1.0, 2.0], [0, 0]))
    rng = np.random.default_rng(1)
    for _ in range(20):
        scores = rng.integers(0, 6, 25).astype(float)
        labels = rng.random(25) < 0.3
        if labels.any():
            assert average_precision(scores, labels) == pytest.approx(_loop_average_precision(scores, labels))


# ------------------------------------------------------------------------------------------------ episode bootstrap

def test_cluster_counts_draw_whole_episodes_within_strata():
    strata = np.array([0, 0, 0, 1, 1])
    counts = cluster_counts(strata, n_resamples=200, seed=3)
    assert counts.shape == (200, 5)
    assert (counts[:, :3].sum(axis=1) == 3).all() and (counts[:, 3:].sum(axis=1) == 2).all()
    assert (counts == cluster_counts(strata, n_resamples=200, seed=3)).all()  # seeded: deterministic
    assert (counts != cluster_counts(strata, n_resamples=200, seed=4)).any()
    assert counts.std(axis=0).min() > 0  # every episode is sometimes drawn more, sometimes less often


def test_resampled_metrics_equal_the_metrics_of_the_repeated_episodes():
    rng = np.random.default_rng(2)
    for _ in range(10):
        n, episodes = 40, 6
        scores = rng.integers(0, 6, n).astype(float)
        labels = rng.random(n) < 0.3
        clusters = rng.integers(0, episodes, n)
        counts = rng.integers(0, 3, (4, episodes))
        areas, precisions = ranking_draws(scores, labels, clusters, counts)
        for row, area, precision in zip(counts, areas, precisions, strict=True):
            # the data set this resample stands for: each episode's steps repeated `count` times
            rows = np.concatenate([np.tile(np.flatnonzero(clusters == e), c) for e, c in enumerate(row)]).astype(int)
            expected_area, expected_ap = auroc(scores[rows], labels[rows]), average_precision(scores[rows],
                                                                                              labels[rows])
            assert (np.isnan(area) and np.isnan(expected_area)) or area == pytest.approx(expected_area)
            assert (np.isnan(precision) and np.isnan(expected_ap)) or precision == pytest.approx(expected_ap)


def test_identical_episodes_give_no_spread_where_a_step_bootstrap_would():
    # ten copies of one episode: resampling EPISODES cannot change the AUROC; resampling steps would
    scores = np.tile([0.1, 0.9, 0.5, 0.4], 10)
    labels = np.tile([False, True, False, True], 10)
    clusters = np.repeat(np.arange(10), 4)
    counts = cluster_counts(np.zeros(10), n_resamples=300, seed=0)
    draws, _ = ranking_draws(scores, labels, clusters, counts)
    assert np.allclose(draws, auroc(scores, labels))  # 0.75 in every resample
    step_counts = cluster_counts(np.zeros(40), n_resamples=300, seed=0)
    step_draws, _ = ranking_draws(scores, labels, np.arange(40), step_counts)
    assert step_draws.std() > 0.01
    interval = percentile_interval(0.75, draws)
    assert interval.low == interval.high == pytest.approx(0.75)


def test_percentile_interval_and_bonferroni_level():
    draws = np.arange(1001) / 1000.0
    interval = percentile_interval(0.5, draws, confidence=0.9)
    assert interval.low == pytest.approx(0.05) and interval.high == pytest.approx(0.95)
    assert np.isnan(percentile_interval(0.5, np.full(10, np.nan)).low)  # no defined resample: no interval
    assert bonferroni_confidence(0.95, 25) == pytest.approx(0.998)


# ------------------------------------------------------------------------------------------------ label and state

def test_collision_label_marks_the_last_second_of_a_collision_episode():
    episode = np.array([0] * 7 + [1] * 5 + [2] * 2)
    step = np.r_[np.arange(7), np.arange(5), np.arange(2)]
    outcome = np.array([""] * 6 + ["collision"] + [""] * 4 + ["goal"] + ["", "collision"], dtype=object)
    label = collision_soon(episode, step, outcome, horizon=4)
    # episode 0 collides in the step of row 6: rows 3, 4, 5, 6 are within 4 steps; goal episodes: none
    assert label.tolist() == [False] * 3 + [True] * 4 + [False] * 5 + [True, True]


def _episode(episode: int, gaps: list[float], outcome: str, speeds: list[float] | None = None, **columns):
    n = len(gaps)
    frame = pd.DataFrame({"estimator": "mc", "perturbation": "observation_noise", "strength": 0.0,
                          "episode": episode, "step": np.arange(n), "nearest_gap": gaps,
                          "nearest_relative_speed": speeds if speeds is not None else [0.0] * n,
                          "outcome": [""] * (n - 1) + [outcome]})
    for name, values in columns.items():
        frame[name] = values
    return frame


def test_proximity_state_is_the_one_at_the_decision():
    # nearest_gap of a row is the gap AFTER its step: the rule at row t reads the gap of row t - 1
    steps = _episode(0, [3.0, 1.0, 0.5, 0.6, 0.2], "goal", speeds=[0.0, 0.2, 0.4, 1.0, 0.0])
    frame = prepare_steps(steps)
    assert frame["step"].tolist() == [1, 2, 3, 4]  # the first row has no d(t)
    assert frame["gap"].tolist() == [3.0, 1.0, 0.5, 0.6]
    assert np.isnan(frame["previous_gap"][0]) and frame["previous_gap"].tolist()[1:] == [3.0, 1.0, 0.5]
    assert frame["score"].tolist() == pytest.approx([3.0, 1.1, 0.7, 1.1])  # d + 0.5 |dv| of the previous row
    assert frame["c_prox"].tolist() == [False, False, True, False]
    assert frame["c_ap"].tolist() == [True, True, True, False]  # unknown d(t - 1): approaching
    assert frame["proximity"].tolist() == [False, False, True, False]


# Two episodes (rows listed from step 1; step 0 holds the gap the rule reads at step 1):
#   episode 0 collides: d(t) = 2.0, 1.5, 1.0, 0.6, 0.3 -> labels F T T T T; proximity at d = 0.6, 0.3 (both positive)
#   episode 1 misses:   d(t) = 2.0, 1.0, 0.5, 0.4, 0.8 -> all negative; proximity at d = 0.5, 0.4 (0.8: receding)
HAND = pd.concat([
    _episode(0, [2.0, 1.5, 1.0, 0.6, 0.3, 0.1], "collision",
             u_ep_heading=[0.5, 0.5, 0.5, 0.5, 0.9, 0.8], u_feat=[0.0, 0.0, 0.0, 0.0, 1.0, 1.0]),
    _episode(1, [2.0, 1.0, 0.5, 0.4, 0.8, 2.0], "goal",
             u_ep_heading=[0.5, 0.5, 0.5, 0.2, 0.3, 0.5], u_feat=[0.0, 0.0, 0.0, 1.0, 1.0, 1.0]),
], ignore_index=True)


def test_ranking_within_the_proximity_firing_steps_by_hand():
    table = information_table(HAND, measures=["u_ep_heading", "u_feat"], n_resamples=50, incremental=False)
    rows = table[table["scope"] == "all"].set_index("measure")
    ep, feat = rows.loc["u_ep_heading"], rows.loc["u_feat"]
    assert (ep["steps"], ep["positives"], ep["proximity_steps"], ep["proximity_positives"]) == (10, 4, 4, 2)
    # alone: positives 0.5, 0.5, 0.9, 0.8 vs negatives 0.5 x 4, 0.2, 0.3 -> (2 * 6 + 2 * (2 + 4 / 2)) / 24
    assert ep["auroc"] == pytest.approx(20 / 24)
    # precision at 0.9, 0.8: 1, 1 (recall 1/4 each); at 0.5: 4/8 (recall 1/2 more)
    assert ep["auprc"] == pytest.approx(0.25 + 0.25 + 0.5 * 0.5)
    # given proximity: 0.9, 0.8 (collision) vs 0.2, 0.3 (miss) -- perfect; u_feat is 1 at all four: chance
    assert ep["proximity_auroc"] == 1.0 and ep["proximity_auprc"] == 1.0
    assert feat["proximity_auroc"] == 0.5 and feat["proximity_auprc"] == pytest.approx(0.5)
    assert ep["proximity_base_rate"] == 0.5 and ep["base_rate"] == pytest.approx(0.4)


def test_gate_diagnostics_by_hand():
    steps = HAND.assign(w_u_ep_heading=HAND["u_ep_heading"], w_u_feat=HAND["u_feat"])
    paper = gate_diagnostics(steps).iloc[0]  # MC-dropout: lambda_ep 0.03, lambda_f 0.3
    assert paper["proximity_steps"] == 4 and paper["gate_open_pct"] == 100.0  # every u_ep > 0.03: never a veto
    assert paper["c_feat_pct"] == 100.0 and paper["collisions"] == 1 and paper["collisions_rule_fired_pct"] == 100.0
    strict = gate_diagnostics(steps, {"mc": (0.85, 5.0)}).iloc[0]
    assert strict["c_ep_pct"] == 25.0 and strict["gate_open_pct"] == 25.0  # only the 0.9 passes 0.85
    assert strict["collisions_rule_fired_pct"] == 100.0 and strict["collisions_proximity_fired_pct"] == 100.0
    assert strict["spearman_w_u_feat_gap"] < 0  # higher where the human is near


def test_logistic_fit_and_cross_fitting():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(4000, 2))
    y = rng.random(4000) < 1 / (1 + np.exp(-(-1.0 + 2.0 * x[:, 0])))
    w = fit_logistic(x, y, l2=0.0)
    assert w == pytest.approx([-1.0, 2.0, 0.0], abs=0.15)
    clusters = np.repeat(np.arange(400), 10)
    scores = cross_fitted_scores(x, y, clusters)
    assert auroc(scores, y) == pytest.approx(auroc(x[:, 0], y), abs=0.01)


# ------------------------------------------------------------------------------------------------ Table 2 claims

def _means(estimator: str, perturbation: str, strength: float, **columns: list[float]) -> pd.DataFrame:
    n = len(next(iter(columns.values())))
    return pd.DataFrame({"estimator": estimator, "perturbation": perturbation, "strength": strength,
                         "episode": np.arange(n), **columns})


def _claims_data() -> pd.DataFrame:
    wobble = np.tile([-0.1, 0.1], 20)  # 40 episodes, mean 0
    frames = []
    for estimator, feat0, feat2, speed0, speed2 in (("mc", 1.0, 3.0, 1.0, 1.0), ("ensemble", 1.0, 1.2, 1.0, 1.5)):
        frames.append(_means(estimator, "observation_noise", 0.0, u_feat=feat0 + wobble, u_ep_speed=speed0 + wobble,
                             u_al_heading=0.5 + wobble / 10, u_ep_heading=0.1 + wobble / 10,
                             u_al_speed=0.2 + wobble / 10))
        frames.append(_means(estimator, "observation_noise", 2.0, u_feat=feat2 + wobble, u_ep_speed=speed2 + wobble,
                             u_al_heading=0.5 + wobble / 10, u_ep_heading=0.5 + wobble / 10,
                             u_al_speed=0.6 + wobble / 10))
        frames.append(_means(estimator, "more_humans", 2.0, u_feat=1.0 + wobble, u_ep_speed=1.0 + wobble,
                             u_al_heading=0.5 + wobble / 10, u_ep_heading=0.1 + wobble / 10,
                             u_al_speed=0.2 + wobble / 10))
        frames.append(_means(estimator, "more_humans", 7.0, u_feat=9.0 + wobble, u_ep_speed=1.0 + wobble,
                             u_al_heading=0.5 + wobble / 10, u_ep_heading=0.5 + wobble / 10,
                             u_al_speed=0.6 + wobble / 10))
    return pd.concat(frames, ignore_index=True)


def test_mc_vs_ensemble_compares_magnitudes_with_paired_intervals():
    table = mc_vs_ensemble_frame(_claims_data(), n_resamples=2000).set_index(["perturbation", "uncertainty"])
    # u_feat, observation noise: MC (3 - 1) / (1 * 2) = 1, ensemble (1.2 - 1) / 2 = 0.1 -> 0.9
    feat = table.loc[("observation_noise", "u_feat")]
    assert feat["estimate"] == pytest.approx(0.9) and feat["verdict"] == HOLDS and feat["low"] > 0
    # u_ep_speed: MC flat (0), ensemble (1.5 - 1) / 2 = 0.25: the ensemble responds more strongly
    speed = table.loc[("observation_noise", "u_ep_speed")]
    assert speed["estimate"] == pytest.approx(-0.25) and speed["verdict"] == DOES_NOT_HOLD
    # identical sensitivities in both estimators (paired): exactly 0 in every resample -> cannot tell
    same = table.loc[("observation_noise", "u_ep_heading")]
    assert same["estimate"] == pytest.approx(0.0) and same["verdict"] == CANNOT_TELL
    # Bonferroni over the 10 cells (2 perturbation types x 5 uncertainties)
    assert len(table) == 10 and np.allclose(table["confidence"], 1 - 0.05 / 10)
    assert (table["episodes"] == 40).all() and (table["claim"] == CLAIM_MC_STRONGER).all()
    summary = claims_summary(table.reset_index()).set_index("claim").loc[CLAIM_MC_STRONGER]
    # MC larger: u_feat under observation noise; the ensemble larger: u_ep_speed there; the rest identical
    assert (summary["holds"], summary["cannot_tell"], summary["does_not_hold"]) == (1, 8, 1)
    assert summary["verdict"] == DOES_NOT_HOLD  # the paper claims every cell


def test_a_strong_decrease_counts_as_a_strong_response():
    data = pd.concat([_means("mc", "observation_noise", 0.0, u_feat=[2.0, 2.0]),
                      _means("mc", "observation_noise", 2.0, u_feat=[1.0, 1.0]),
                      _means("ensemble", "observation_noise", 0.0, u_feat=[1.0, 1.0]),
                      _means("ensemble", "observation_noise", 2.0, u_feat=[1.1, 1.1])], ignore_index=True)
    row = mc_vs_ensemble_frame(data, n_resamples=200).iloc[0]
    assert row["estimate"] == pytest.approx(0.25 - 0.05)  # |-0.25| - |0.05|


def test_heading_vs_speed_and_more_humans_claims():
    data = _claims_data()
    table = heading_vs_speed_frame(data, n_resamples=2000).set_index(["estimator", "uncertainty", "perturbation"])
    assert len(table) == 8 and (table["claim"] == CLAIM_HEADING_RISES).all()
    # epistemic: heading 0.1 -> 0.5, speed flat (MC) -> 0.4 - 0: holds
    mc_ep = table.loc[("mc", "epistemic", "observation_noise")]
    assert mc_ep["estimate"] == pytest.approx(0.4) and mc_ep["verdict"] == HOLDS
    # ensemble epistemic on observation noise: speed rises by 0.5, more than heading's 0.4
    ens_ep = table.loc[("ensemble", "epistemic", "observation_noise")]
    assert ens_ep["estimate"] == pytest.approx(-0.1) and ens_ep["verdict"] == DOES_NOT_HOLD
    # aleatoric: heading flat, speed rises 0.4: does not hold
    assert table.loc[("mc", "aleatoric", "more_humans"), "verdict"] == DOES_NOT_HOLD
    humans = more_humans_frame(data, n_resamples=2000).set_index(["estimator", "uncertainty"])
    assert (humans["claim"] == CLAIM_MORE_HUMANS).all() and len(humans) == 10
    # u_feat: 9 with 7 agents vs 3 (MC) at the strongest observation noise
    assert humans.loc[("mc", "u_feat"), "estimate"] == pytest.approx(6.0)
    assert humans.loc[("mc", "u_feat"), "verdict"] == HOLDS
    # u_ep_heading: 0.5 in both: no difference
    assert humans.loc[("mc", "u_ep_heading"), "verdict"] == CANNOT_TELL
