"""The navigation metrics (socnav.sim.metrics) against hand-computed values on scripted trajectories, their invariants
on rollouts, and the registry: one definition per metric, its summaries equal to the last bit to the arithmetic
written out directly."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from socnav.config import load_config
from socnav.controllers import OrcaController
from socnav.envs.rollout import EPISODE_COLUMNS, rollout_episodes, summarize
from socnav.sim.metrics import (
    ALL_METRICS,
    DEFAULT_METRICS,
    METRIC_RECORD_COLUMNS,
    METRICS,
    TTC_HORIZON,
    episode_values,
    select_metrics,
    summarize_episodes,
    summarize_groups,
    time_to_collision,
)
from socnav.sim.scenarios import InitialState
from socnav.sim.world import OUTCOME_GOAL, CrowdWorld

DT = 0.25
FULL_SPEED, STAND = [1.0, 0.0], [-1.0, 0.0]  # actions: v_pref straight on / speed 0


def staged(robot, goal, humans=(), **config) -> CrowdWorld:
    """One environment accumulating metrics: the robot (v_pref 1 m/s, radius 0.3) at `robot` facing `goal`; humans
    as (position, goal, personal-space radius), radius 0.3, v_pref 1 m/s; humans do not see the robot (they walk
    straight to their goal, or stand on it)."""
    cfg = load_config({"scenario": "circle_crossing", "n_humans": len(humans), "human_fov_deg": 360,
                       "robot_visible": False, "reward": {"disturbance": 0.0}, **config})
    world = CrowdWorld(cfg, 1, metrics=True)
    state = InitialState.empty(1, world.n_slots)
    state.positions[0, 0], state.goals[0, 0] = robot, goal
    state.radii[0, 0], state.preferred_speeds[0, 0], state.active[0, 0] = 0.3, 1.0, True
    for k, (position, human_goal, personal_space) in enumerate(humans, start=1):
        state.positions[0, k], state.goals[0, k] = position, human_goal
        state.radii[0, k], state.preferred_speeds[0, k], state.active[0, k] = 0.3, 1.0, True
        state.personal_space_radii[0, k], state.cooperation[0, k] = personal_space, 0.5
    state.robot_heading[0] = math.atan2(goal[1] - robot[1], goal[0] - robot[0])
    world.load(0, state)
    return world


def play(world: CrowdWorld, actions) -> tuple[dict, int]:
    """Step through `actions` until the episode ends; the summary and the outcome of the last step."""
    outcome = 0
    for action in actions:
        outcome = int(world.step(np.array([action])).outcome[0])
        if outcome:
            break
    return world.episode_summary(0, outcome), outcome


# ------------------------------------------------------------------------------------------------------------------
# Scripted trajectories, hand-computed values


def test_straight_drive_past_a_standing_human():
    # The robot drives east at 1 m/s from (0, 0) to its goal (6, 0): x_k = 0.25 k; it is within the goal tolerance
    # 0.3 after k = 23 steps (x = 5.75). A human stands on its goal at (3, 1), personal-space radius 0.5: its gap is
    # g_k = sqrt((3 - x_k)^2 + 1) - 0.6.
    world = staged((0.0, 0.0), (6.0, 0.0), [((3.0, 1.0), (3.0, 1.0), 0.5)])
    summary, outcome = play(world, [FULL_SPEED] * 40)
    assert outcome == OUTCOME_GOAL and summary["length"] == 23
    assert world.positions[0, 1] == pytest.approx([3.0, 1.0]), "the human stood still"
    steps = 23
    assert summary["success"] and not summary["collision_human"] and not summary["timeout"]
    assert not summary["collision_obstacle"]
    # Path: 23 x 0.25 m = 5.75 m against a straight line of 6 m; SPL = 6 / max(5.75, 6) = 1.
    assert summary["path_length_ratio"] == pytest.approx(5.75 / 6.0)
    assert summary["spl"] == pytest.approx(1.0)
    # Inside the personal space (g < 0.5: |3 - x| < 0.458): x = 2.75, 3.0, 3.25, one entry, the robot driving at
    # the human (v . (p_h - p_r) = 0.25 > 0): robot-caused.
    assert summary["intrusion_steps"] == 3 and summary["intrusion_events"] == 1
    assert (summary["intrusions_robot"], summary["intrusions_human"]) == (1, 0)
    assert summary["personal_space_compliance"] == pytest.approx(100.0 * (1 - 3 / steps))
    # Zones: intimate g < 0.45 (|3 - x| < 0.32): 3 steps; personal g < 1.2 (|3 - x| < 1.497): x = 1.75 .. 4.25,
    # 11 steps; social g < 3.6 (|3 - x| < 4.08): every step.
    assert summary["intimate_zone_time"] == pytest.approx(100.0 * 3 / steps)
    assert summary["personal_zone_time"] == pytest.approx(100.0 * 11 / steps)
    assert summary["social_zone_time"] == pytest.approx(100.0)
    assert summary["min_gap"] == pytest.approx(0.4)
    # Constant 1 m/s from rest: a_1 = 4 m/s^2 then 0; j_1 = 16, j_2 = -16 m/s^3, then 0.
    assert summary["speed_mean"] == pytest.approx(1.0) and summary["speed_max"] == pytest.approx(1.0)
    assert summary["acceleration_mean"] == pytest.approx(4.0 / steps)
    assert summary["acceleration_max"] == pytest.approx(4.0)
    assert summary["jerk_mean"] == pytest.approx(32.0 / steps) and summary["jerk_max"] == pytest.approx(16.0)
    # Heading 0 straight at the goal from every step's start; never slower than 0.05 m/s; always progressing.
    assert summary["path_irregularity"] == pytest.approx(0.0, abs=1e-12)
    assert summary["stalled_time"] == 0.0 and not summary["failure_to_progress"]
    # Passing 1 m to the side of a standing human (combined radius 0.6): never on a collision course.
    assert summary["min_time_to_collision"] == TTC_HORIZON


def test_polyline_path_irregularity_and_path_ratio():
    # Goal (10, 0). Step 1: turn left pi/6 and drive 0.25 m; step 2: turn back to heading 0 and drive 0.25 m; then
    # stand still. Step 1's heading pi/6 against the goal direction 0 from (0, 0); step 2's heading 0 against the
    # direction from p_1 = 0.25 (cos pi/6, sin pi/6) to the goal; standing steps: heading 0 against the direction
    # from p_2 = p_1 + (0.25, 0).
    world = staged((0.0, 0.0), (10.0, 0.0))
    summary, _ = play(world, [[1.0, 1.0], [1.0, -1.0], STAND, STAND])
    p1 = 0.25 * np.array([math.cos(math.pi / 6), math.sin(math.pi / 6)])
    p2 = p1 + np.array([0.25, 0.0])
    off_1 = abs(math.atan2(0.0 - p1[1], 10.0 - p1[0]))
    off_2 = abs(math.atan2(0.0 - p2[1], 10.0 - p2[0]))
    assert summary["path_irregularity"] == pytest.approx((math.pi / 6 + off_1 + 2 * off_2) / 4, rel=1e-12)
    assert world.positions[0, 0] == pytest.approx(p2)
    # Not at the goal: no path ratio (NaN) and SPL 0; two of four steps standing still: 0.5 s stalled.
    assert math.isnan(summary["path_length_ratio"]) and summary["spl"] == 0.0
    assert summary["stalled_time"] == pytest.approx(0.5)
    assert summary["path_length"] == pytest.approx(0.5)


def test_stop_and_go_jerk():
    # Speeds 1, 1, 0, 0, 1, 1 m/s east (dt 0.25): a = 4, 0, -4, 0, 4, 0 m/s^2; j = 16, -16, -16, 16, 16, -16 m/s^3.
    world = staged((0.0, 0.0), (30.0, 0.0))
    summary, _ = play(world, [FULL_SPEED, FULL_SPEED, STAND, STAND, FULL_SPEED, FULL_SPEED])
    assert summary["length"] == 6
    assert summary["speed_mean"] == pytest.approx(4 / 6) and summary["speed_max"] == pytest.approx(1.0)
    assert summary["acceleration_mean"] == pytest.approx(12 / 6) and summary["acceleration_max"] == pytest.approx(4.0)
    assert summary["jerk_mean"] == pytest.approx(16.0) and summary["jerk_max"] == pytest.approx(16.0)
    assert summary["stalled_time"] == pytest.approx(0.5)


def test_turning_in_place_and_on_a_curve_is_acceleration():
    # At 1 m/s, heading turned by pi/6 between steps: |a| = |v_2 - v_1| / dt = 2 sin(pi/12) / 0.25.
    world = staged((0.0, 0.0), (30.0, 0.0))
    summary, _ = play(world, [FULL_SPEED, [1.0, 1.0]])
    assert summary["acceleration_max"] == pytest.approx(4.0)
    assert summary["acceleration_mean"] == pytest.approx((4.0 + 2 * math.sin(math.pi / 12) / DT) / 2)


def test_head_on_time_to_collision():
    # Robot east at 1 m/s from (0, 0), a human west at 1 m/s from (5, 0): after step k the centres are 5 - 0.5 k
    # apart, closing at 2 m/s, touching at 0.6 m: TTC_k = (4.4 - 0.5 k) / 2 (1.95 s after one step).
    world = staged((0.0, 0.0), (20.0, 0.0), [((5.0, 0.0), (-20.0, 0.0), 0.3)])
    world.step(np.array([FULL_SPEED]))
    assert world.velocities[0, 1] == pytest.approx([-1.0, 0.0])
    assert world.episode_summary(0, 0)["min_time_to_collision"] == pytest.approx(1.95)
    world.step(np.array([FULL_SPEED]))
    assert world.episode_summary(0, 0)["min_time_to_collision"] == pytest.approx(1.7)
    summary, _ = play(world, [FULL_SPEED] * 20)
    assert summary["outcome"] == "collision" and summary["collision_human"]
    assert summary["min_time_to_collision"] == 0.0 and not summary["success"]


@pytest.mark.parametrize(("rel", "velocity", "expected"), [
    ((5.0, 0.0), (-2.0, 0.0), 2.2),  # head-on: (5 - 0.6) / 2
    ((3.0, 0.3), (-1.0, 0.0), 3.0 - math.sqrt(0.6 ** 2 - 0.3 ** 2)),  # grazing: (3 - t)^2 + 0.09 = 0.36
    ((5.0, 1.0), (-2.0, 0.0), math.inf),  # passes 1 m to the side
    ((5.0, 0.0), (2.0, 0.0), math.inf),  # moving apart
    ((5.0, 0.0), (0.0, 0.0), math.inf),  # both at rest
    ((0.5, 0.0), (1.0, 0.0), 0.0),  # already overlapping
])
def test_time_to_collision_hand_computed(rel, velocity, expected):
    assert time_to_collision(*rel, *velocity, 0.6) == pytest.approx(expected)


def test_a_human_walking_into_a_standing_robot_is_human_caused():
    # The robot stands still (facing its goal to the north); a human walks at it from (2, 0): gap x - 0.6 drops
    # below its personal-space radius 0.5 at x = 1.0, the 4th step.
    world = staged((0.0, 0.0), (0.0, 9.0), [((2.0, 0.0), (-9.0, 0.0), 0.5)])
    for _ in range(4):
        world.step(np.array([STAND]))
    summary = world.episode_summary(0, 0)
    assert summary["intrusion_events"] == 1
    assert (summary["intrusions_robot"], summary["intrusions_human"]) == (0, 1)


def test_failure_to_progress_after_five_seconds_without_progress():
    # Standing still: no progress since t = 0; the window of 5 s closes at step 20 (t = 5.0 s).
    world = staged((0.0, 0.0), (30.0, 0.0))
    for _ in range(19):
        world.step(np.array([STAND]))
    assert not world.episode_summary(0, 0)["failure_to_progress"]
    world.step(np.array([STAND]))
    summary = world.episode_summary(0, 0)
    assert summary["failure_to_progress"] and summary["stalled_time"] == pytest.approx(5.0)
    # Driving on does not undo it: it happened in this episode.
    world.step(np.array([FULL_SPEED]))
    assert world.episode_summary(0, 0)["failure_to_progress"]


def test_wall_collision_hook_marks_obstacle_collisions():
    world = staged((0.0, 0.0), (30.0, 0.0))
    world.step(np.array([FULL_SPEED]))
    assert not world.episode_summary(0, 0)["collision_obstacle"], "always False without obstacle code"
    world.wall_collision[0] = True  # what obstacle code does in the step the robot hits a wall
    summary = world.episode_summary(0, 2)  # outcome: collision
    assert summary["collision_obstacle"] and not summary["collision_human"]
    world.load(0, _initial(world))
    assert not world.wall_collision[0], "cleared at every episode start"


def _initial(world: CrowdWorld) -> InitialState:
    state = InitialState.empty(1, world.n_slots)
    state.goals[0, 0], state.radii[0, 0], state.preferred_speeds[0, 0], state.active[0, 0] = (5.0, 0.0), 0.3, 1.0, True
    return state


# ------------------------------------------------------------------------------------------------------------------
# Rollouts: invariants, and the metrics change nothing else


@pytest.mark.parametrize("scenario", ["circle_crossing", "random"])
def test_metrics_change_no_other_record_and_hold_their_invariants(scenario):
    config = load_config({"scenario": scenario, "perturbation": {"heading_noise": 0.3}})
    policy = OrcaController(config)
    plain = rollout_episodes(policy, config, 12, seed=3, n_envs=5, metrics=False)
    full = rollout_episodes(policy, config, 12, seed=3, n_envs=5)
    assert list(plain.columns) == list(EPISODE_COLUMNS)
    assert list(full.columns) == [*EPISODE_COLUMNS, *METRIC_RECORD_COLUMNS]
    pd.testing.assert_frame_equal(full[list(EPISODE_COLUMNS)], plain, check_exact=True)
    # batch-size independence holds for the metric columns too
    alone = rollout_episodes(policy, config, 12, seed=3, n_envs=1)
    pd.testing.assert_frame_equal(alone, full, check_exact=True)

    assert (full["intrusions_robot"] + full["intrusions_human"] == full["intrusion_events"]).all()
    assert (full["success"] == (full["outcome"] == "goal")).all()
    assert (full["collision_human"] == (full["outcome"] == "collision")).all()
    assert (full["timeout"] == (full["outcome"] == "timeout")).all() and not full["collision_obstacle"].any()
    assert (full["collision_human"] == (full["min_gap"] < 0)).all()
    assert full["spl"].between(0.0, 1.0).all() and (full.loc[~full["success"], "spl"] == 0.0).all()
    assert full["path_length_ratio"].isna().equals(~full["success"])
    np.testing.assert_allclose(full["personal_space_compliance"],
                               100.0 * (1 - full["intrusion_steps"] / full["length"]))
    assert (full["intimate_zone_time"] <= full["personal_zone_time"]).all()
    assert (full["personal_zone_time"] <= full["social_zone_time"]).all()
    assert full["min_time_to_collision"].between(0.0, TTC_HORIZON).all()
    assert (full["stalled_time"] <= full["duration"] + 1e-9).all()
    assert (full["speed_mean"] <= full["speed_max"] + 1e-12).all()
    assert (full["jerk_mean"] <= full["jerk_max"] + 1e-12).all()
    np.testing.assert_allclose(full["speed_mean"] * full["duration"], full["path_length"], rtol=1e-9)


# ------------------------------------------------------------------------------------------------------------------
# The registry


def test_every_metric_is_defined_once_with_unit_direction_and_source():
    assert len(set(ALL_METRICS)) == len(METRICS)
    for name, metric in METRICS.items():
        assert metric.name == name and metric.definition and metric.source and metric.label
        assert metric.higher_is_better in (True, False, None)
        assert metric.column in (*EPISODE_COLUMNS, *METRIC_RECORD_COLUMNS), f"{name} reads no record column"
    assert DEFAULT_METRICS == ("goal_pct", "collision_pct", "timeout_pct", "pv", "return_mean", "return_std",
                               "time_to_goal_mean")


def test_docs_list_every_metric():
    text = (Path(__file__).resolve().parents[2] / "docs" / "metrics.md").read_text()
    for name in METRICS:
        assert f"`{name}`" in text, f"docs/metrics.md does not list {name}"


def test_select_metrics():
    assert select_metrics("default") == list(DEFAULT_METRICS)
    assert select_metrics("all") == list(ALL_METRICS)
    assert select_metrics(" spl, jerk_max ,spl") == ["spl", "jerk_max"]
    with pytest.raises(ValueError, match=r"unknown metric 'spll' \(did you mean 'spl'\?\).*goal_pct"):
        select_metrics("spl,spll")
    with pytest.raises(ValueError, match="allowed: default, all"):
        select_metrics(" , ")


def _records(rng: np.random.Generator, n: int) -> pd.DataFrame:
    outcome = rng.choice(["goal", "collision", "timeout"], n, p=[0.6, 0.15, 0.25])
    return pd.DataFrame({
        "group": rng.choice(["a", "b", "c"], n), "seed": rng.integers(0, 3, n), "outcome": outcome,
        "intrusion_events": rng.integers(0, 5, n), "return": rng.normal(0.0, 3.0, n),
        "time_to_goal": np.where(outcome == "goal", rng.uniform(5, 30, n), np.nan),
    })


def _direct_summarize(records, pv_per=200):
    """`socnav.envs.rollout.summarize`'s arithmetic written out directly, without the metrics registry: its oracle
    to the last bit."""
    n = len(records)
    share = lambda outcome: 100.0 * float((records["outcome"] == outcome).mean())  # noqa: E731
    return {"episodes": n, "goal_pct": share("goal"), "collision_pct": share("collision"),
            "timeout_pct": share("timeout"), "pv": float(records["intrusion_events"].sum()) * pv_per / n,
            "return_mean": float(records["return"].mean()), "return_std": float(records["return"].std(ddof=0)),
            "time_to_goal_mean": float(records["time_to_goal"].mean())}


def _direct_table1_seed_frame(records, by, pv_per=200):
    """The per-seed Table 1 frame (`summarize_groups` of its metrics) written out directly with pandas, without the
    metrics registry."""
    outcome = records["outcome"]
    per_episode = records.assign(goal=(outcome == "goal") * 100.0, collision=(outcome == "collision") * 100.0,
                                 timeout=(outcome == "timeout") * 100.0)
    per_seed = per_episode.groupby(by, sort=False).agg(
        episodes=("return", "size"), goal_pct=("goal", "mean"), collision_pct=("collision", "mean"),
        timeout_pct=("timeout", "mean"), events=("intrusion_events", "sum"), return_mean=("return", "mean"),
    ).reset_index()
    per_seed["pv"] = per_seed["events"] * pv_per / per_seed["episodes"]
    return per_seed[[*by, "episodes", "goal_pct", "collision_pct", "timeout_pct", "pv", "return_mean"]]


@pytest.mark.parametrize("seed", range(20))
def test_the_registry_summaries_equal_the_direct_arithmetic_to_the_last_bit(seed):
    rng = np.random.default_rng(seed)
    records = _records(rng, int(rng.integers(1, 500)))
    registry, direct = summarize(records), _direct_summarize(records)
    assert list(registry) == list(direct)
    for key in direct:
        assert registry[key] == direct[key] or (math.isnan(registry[key]) and math.isnan(direct[key])), key
    names = ["goal_pct", "collision_pct", "timeout_pct", "pv", "return_mean"]
    grouped = summarize_groups(records, ["group", "seed"], names)
    pd.testing.assert_frame_equal(grouped, _direct_table1_seed_frame(records, ["group", "seed"]), check_exact=True)


def test_summaries_per_kind_hand_computed():
    records = pd.DataFrame({"outcome": ["goal", "goal", "collision", "timeout"], "intrusion_events": [1, 0, 2, 1],
                            "return": [4.0, 2.0, -6.0, 0.0], "time_to_goal": [10.0, 20.0, np.nan, np.nan],
                            "spl": [1.0, 0.5, 0.0, 0.0]})
    summary = summarize_episodes(records, ["goal_pct", "pv", "return_mean", "return_std", "time_to_goal_mean",
                                           "spl", "jerk_max"])
    assert summary["episodes"] == 4 and summary["goal_pct"] == 50.0 and summary["pv"] == 4 * 200 / 4
    assert summary["return_mean"] == 0.0 and summary["return_std"] == pytest.approx(math.sqrt(14.0))
    assert summary["time_to_goal_mean"] == 15.0 and summary["spl"] == 0.375
    assert math.isnan(summary["jerk_max"]), "a metric without its record column is undefined"
    np.testing.assert_array_equal(episode_values(records, "goal_pct"), [100.0, 100.0, 0.0, 0.0])
    np.testing.assert_array_equal(episode_values(records, "pv"), [200, 0, 400, 200])
    np.testing.assert_array_equal(episode_values(records, "time_to_goal_mean"), [10.0, 20.0])
    grouped = summarize_groups(records.assign(g=["x", "x", "y", "y"]), ["g"], ["goal_pct", "spl", "jerk_max"])
    assert list(grouped.columns) == ["g", "episodes", "goal_pct", "spl"], "metrics without a column are left out"
    assert grouped["goal_pct"].tolist() == [100.0, 0.0] and grouped["spl"].tolist() == [0.75, 0.0]
