"""Reports read the metrics registry: Table 1's and Table 3's numbers equal a direct pandas computation to the last
bit, and their CSVs hold every other metric the records hold, computed as an independent per-seed / per-group loop
computes it."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from socnav.paper.table1.tables import EXTRA_METRICS, TABLE1_COLUMNS, table1_frame, table1_seed_frame
from socnav.paper.uncertainty.table3 import episode_rates, safety_metrics_frame
from socnav.sim.metrics import METRIC_RECORD_COLUMNS

ID = ["train_scenario", "algo", "eval_scenario"]


def _records(rng: np.random.Generator, metrics: bool) -> pd.DataFrame:
    frames = []
    for train in ("circle_crossing", "random"):
        for algo in ("ppo", "odv-ppo-drop"):
            for seed in range(3):
                for evaluation in ("position_swap", "random"):
                    n = int(rng.integers(1, 40))
                    outcome = rng.choice(["goal", "collision", "timeout"], n, p=[0.6, 0.15, 0.25])
                    frame = pd.DataFrame({
                        "train_scenario": train, "algo": algo, "train_seed": seed, "eval_scenario": evaluation,
                        "episode": np.arange(n), "outcome": outcome, "return": rng.normal(1.0, 3.0, n),
                        "intrusion_events": rng.integers(0, 4, n),
                        "time_to_goal": np.where(outcome == "goal", rng.uniform(5, 30, n), np.nan),
                        "path_length": rng.uniform(5, 20, n), "min_gap": rng.uniform(-0.1, 2, n),
                        "disturbance": rng.uniform(0, 10, n),
                    })
                    if metrics:
                        for column in METRIC_RECORD_COLUMNS:
                            frame[column] = rng.uniform(0, 5, n)
                        frame["success"] = outcome == "goal"
                        frame["collision_human"] = outcome == "collision"
                        frame["intrusions_robot"] = rng.integers(0, 3, n)
                        frame["failure_to_progress"] = rng.random(n) < 0.2
                    frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def _direct_table1_seed_frame(records, pv_per=200):
    """Table 1's per-seed metrics by a direct pandas aggregation, without the metrics registry: the oracle."""
    columns = [*ID, "train_seed", "episodes", "goal_pct", "collision_pct", "timeout_pct", "pv", "return_mean"]
    outcome = records["outcome"]
    per_episode = records.assign(goal=(outcome == "goal") * 100.0, collision=(outcome == "collision") * 100.0,
                                 timeout=(outcome == "timeout") * 100.0)
    per_seed = per_episode.groupby([*ID, "train_seed"], sort=False).agg(
        episodes=("return", "size"), goal_pct=("goal", "mean"), collision_pct=("collision", "mean"),
        timeout_pct=("timeout", "mean"), events=("intrusion_events", "sum"), return_mean=("return", "mean"),
    ).reset_index()
    per_seed["pv"] = per_seed["events"] * pv_per / per_seed["episodes"]
    return per_seed[columns]


@pytest.mark.parametrize("seed", range(5))
def test_table1_matches_the_direct_computation_to_the_last_bit(seed):
    records = _records(np.random.default_rng(seed), metrics=bool(seed % 2))
    direct = _direct_table1_seed_frame(records)
    new = table1_seed_frame(records)
    pd.testing.assert_frame_equal(new[list(direct.columns)], direct, check_exact=True)
    table = table1_frame(records)
    assert list(table.columns[:len(TABLE1_COLUMNS)]) == TABLE1_COLUMNS


def test_table1_csv_holds_every_other_metric_as_the_mean_over_seeds():
    records = _records(np.random.default_rng(11), metrics=True)
    table = table1_frame(records).set_index(ID)
    assert list(table.columns[len(TABLE1_COLUMNS) - len(ID):]) == EXTRA_METRICS
    for key, group in records.groupby(ID):
        per_seed = {name: [] for name in ("spl", "pv_robot", "collision_human_pct", "time_to_goal_mean",
                                          "failure_to_progress_pct")}
        for _, episodes in group.groupby("train_seed"):
            per_seed["spl"].append(episodes["spl"].to_numpy().mean())
            per_seed["pv_robot"].append(episodes["intrusions_robot"].to_numpy().sum() * 200 / len(episodes))
            per_seed["collision_human_pct"].append(100 * episodes["collision_human"].to_numpy().mean())
            per_seed["time_to_goal_mean"].append(np.nanmean(episodes["time_to_goal"].to_numpy())
                                                 if episodes["time_to_goal"].notna().any() else np.nan)
            per_seed["failure_to_progress_pct"].append(100 * episodes["failure_to_progress"].to_numpy().mean())
        row = table.loc[key]
        for name, values in per_seed.items():
            assert row[name] == pytest.approx(np.nanmean(values), rel=1e-12), name


def test_records_without_the_metric_columns_give_table1_columns_only():
    records = _records(np.random.default_rng(3), metrics=False).drop(columns=["path_length", "min_gap",
                                                                             "disturbance", "time_to_goal"])
    assert list(table1_frame(records).columns) == TABLE1_COLUMNS


def _direct_rates(frame, layer):
    """Table 3's rates computed directly from the outcome and step columns, without the metrics registry."""
    n = len(frame)
    goal = frame["outcome"] == "goal"
    time = frame["time_to_goal"] if "time_to_goal" in frame else frame.get("duration")
    activation = math.nan
    if layer and n and "fallback_steps" in frame and frame["length"].sum() > 0:
        activation = 100.0 * float(frame["fallback_steps"].sum()) / float(frame["length"].sum())
    return {"episodes": n, "activation": activation,
            "success": 100.0 * float(goal.mean()) if n else math.nan,
            "collision": 100.0 * float((frame["outcome"] == "collision").mean()) if n else math.nan,
            "time": float(time[goal].astype(float).mean()) if time is not None and goal.any() else math.nan}


@pytest.mark.parametrize("seed", range(10))
def test_table3_rates_match_the_direct_computation_to_the_last_bit(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 300))
    outcome = rng.choice(["goal", "collision", "timeout"], n)
    frame = pd.DataFrame({"outcome": outcome, "length": rng.integers(1, 100, n),
                          "fallback_steps": rng.integers(0, 5, n), "duration": rng.uniform(1, 40, n),
                          "time_to_goal": np.where(outcome == "goal", rng.uniform(1, 40, n), np.nan)})
    variants = [frame, frame.drop(columns="time_to_goal"), frame.drop(columns=["time_to_goal", "duration"])]
    for variant in variants:
        for layer in (True, False):
            direct, new = _direct_rates(variant, layer), episode_rates(variant, layer)
            assert list(direct) == list(new)
            for key in direct:
                assert direct[key] == new[key] or (math.isnan(direct[key]) and math.isnan(new[key])), key


def test_table3_metrics_per_approach_and_perturbed_episodes():
    frame = pd.DataFrame({
        "estimator": "mc", "perturbation": "heading_noise", "strength": [0.0, 0.0, 1.0, 1.0, 0.0, 1.0],
        "variant": ["none", "none", "none", "none", "paper", "paper"], "sensing": ["", "", "", "", "perceived",
                                                                                  "perceived"],
        "outcome": ["goal", "collision", "collision", "collision", "goal", "goal"],
        "spl": [0.9, 0.0, 0.0, 0.0, 0.8, 0.7], "intrusion_events": [1, 0, 2, 2, 0, 1],
    })
    table = safety_metrics_frame(frame).set_index(["variant", "perturbed"])
    assert table.loc[("none", False), "goal_pct"] == 50.0 and table.loc[("none", True), "collision_pct"] == 100.0
    assert table.loc[("paper", True), "spl"] == pytest.approx(0.7) and table.loc[("none", True), "pv"] == 400.0
    assert "jerk_max" not in table, "metrics without their record column are left out"


def test_table2_metrics_per_estimator_perturbation_and_strength(tmp_path):
    from types import SimpleNamespace

    from socnav.io import write_table_atomic
    from socnav.paper.uncertainty.table2 import study_metrics_frame

    episodes = pd.DataFrame({"strength": [0.0, 0.0, 0.5, 0.5], "episode": [0, 1, 0, 1],
                             "outcome": ["goal", "collision", "goal", "goal"], "spl": [0.9, 0.0, 0.7, 0.5],
                             "intrusions_human": [1, 0, 0, 2], "steps_unused": 1})
    write_table_atomic(episodes, tmp_path / "study" / "mc" / "heading_noise" / "episodes.parquet")
    context = SimpleNamespace(results_dir=tmp_path, missing=lambda: [])
    table = study_metrics_frame(context).set_index(["estimator", "perturbation", "strength"])
    row = table.loc[("mc", "heading_noise", 0.5)]
    assert (row["episodes"], row["goal_pct"], row["spl"], row["pv_human"]) == (2, 100.0, pytest.approx(0.6), 200.0)
    assert table.loc[("mc", "heading_noise", 0.0), "collision_pct"] == 50.0
    assert study_metrics_frame(SimpleNamespace(results_dir=tmp_path / "none", missing=lambda: [])).empty
