"""The conversion of a holonomic velocity into the unicycle's action (`socnav.controllers.holonomic_to_unicycle`):
hand-computed actions, and the two ways a robot stopped by a velocity behind it turns."""

from __future__ import annotations

import math

import numpy as np
import pytest

from socnav.config import load_config
from socnav.controllers import OrcaController, holonomic_to_unicycle

MAX_TURN = math.pi / 6


def _observation(heading: float, preferred_speed: float = 1.0) -> dict[str, np.ndarray]:
    """One robot row: distance to goal 4 m, `heading` relative to the goal direction, at rest."""
    return {"robot": np.array([[4.0, heading, 0.0, preferred_speed, 0.3]], dtype=np.float32)}


def test_a_velocity_ahead_is_followed_within_the_turn_limit():
    # desired 0.5 m/s at 20 degrees left of a robot facing the goal: turn 20 degrees, drive 0.5 (no error left)
    desired = 0.5 * np.array([[math.cos(0.35), math.sin(0.35)]])
    speed, turn = holonomic_to_unicycle(desired, _observation(0.0), MAX_TURN)[0]
    assert speed == pytest.approx(2 * 0.5 - 1, abs=1e-6) and turn == pytest.approx(0.35 / MAX_TURN, abs=1e-6)
    # 60 degrees off: the turn is capped at 30 degrees and the speed is 0.5 cos(30 degrees)
    desired = 0.5 * np.array([[math.cos(1.047), math.sin(1.047)]])
    speed, turn = holonomic_to_unicycle(desired, _observation(0.0), MAX_TURN)[0]
    assert turn == pytest.approx(1.0) and speed == pytest.approx(2 * 0.5 * math.cos(1.047 - MAX_TURN) - 1, abs=1e-5)


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_a_velocity_behind_stops_the_robot_and_each_rule_turns_its_way(side):
    """A slow velocity almost straight behind (a wall ahead): the robot stops; by the velocity it turns to the side
    of the velocity's tiny sideways part (the label flips with its sign), by the goal it turns to face the goal
    (here 0.2 rad to its right whatever the sign)."""
    heading = 0.2
    behind = heading + math.pi - side * 0.01  # just off straight behind the robot, on one side or the other
    desired = 0.1 * np.array([[math.cos(behind), math.sin(behind)]])
    by_velocity = holonomic_to_unicycle(desired, _observation(heading), MAX_TURN)[0]
    by_goal = holonomic_to_unicycle(desired, _observation(heading), MAX_TURN, stopped_turn="goal")[0]
    assert by_velocity[0] == pytest.approx(-1.0) and by_goal[0] == pytest.approx(-1.0)  # stopped either way
    assert by_velocity[1] == pytest.approx(side)  # left-behind (side 1): full left; right-behind: full right
    assert by_goal[1] == pytest.approx(-heading / MAX_TURN, abs=1e-6)
    by_goal_if_behind = holonomic_to_unicycle(desired, _observation(heading), MAX_TURN, "goal-if-behind")[0]
    np.testing.assert_array_equal(by_goal_if_behind, by_goal)  # 0.01 rad off straight behind: no clear side


def test_goal_if_behind_turns_towards_a_velocity_with_a_clear_side():
    """Stopped by a velocity 120 degrees to the robot's left (a person coming at it from the front right, say):
    "goal" faces the goal, "goal-if-behind" turns left, towards the velocity, as "velocity" does."""
    desired = 0.3 * np.array([[math.cos(2.1), math.sin(2.1)]])
    observation = _observation(0.0)
    by_velocity, by_goal, by_goal_if_behind = (holonomic_to_unicycle(desired, observation, MAX_TURN, rule)[0]
                                               for rule in ("velocity", "goal", "goal-if-behind"))
    assert by_velocity[0] == pytest.approx(-1.0)  # stopped: cos(2.1 - 0.52) < 0
    assert by_velocity[1] == pytest.approx(1.0) and by_goal[1] == pytest.approx(0.0)
    np.testing.assert_array_equal(by_goal_if_behind, by_velocity)


def test_the_rules_agree_whenever_the_robot_moves():
    generator = np.random.default_rng(0)
    headings = generator.uniform(-math.pi, math.pi, 500)
    angles = generator.uniform(-math.pi, math.pi, 500)
    desired = generator.uniform(0.0, 1.0, 500)[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    observation = {"robot": np.stack([np.full(500, 4.0), headings, np.zeros(500), np.ones(500), np.full(500, 0.3)],
                                     axis=1).astype(np.float32)}
    by_velocity = holonomic_to_unicycle(desired, observation, MAX_TURN)
    by_goal = holonomic_to_unicycle(desired, observation, MAX_TURN, stopped_turn="goal")
    moving = by_velocity[:, 0] > -1.0
    assert 100 < moving.sum() < 500
    np.testing.assert_array_equal(by_velocity[moving], by_goal[moving])
    by_goal_if_behind = holonomic_to_unicycle(desired, observation, MAX_TURN, stopped_turn="goal-if-behind")
    np.testing.assert_array_equal(by_velocity[moving], by_goal_if_behind[moving])
    np.testing.assert_array_equal(by_velocity[:, 0], by_goal[:, 0])


def test_an_unknown_rule_is_a_clear_error():
    with pytest.raises(ValueError, match=r"stopped_turn must be one of \['velocity', 'goal', 'goal-if-behind'\], "
                                         r"got 'left'"):
        holonomic_to_unicycle(np.zeros((1, 2)), _observation(0.0), MAX_TURN, stopped_turn="left")
    with pytest.raises(ValueError, match="stopped_turn must be one of"):
        OrcaController(load_config({"scenario": "doorway"}), stopped_turn="left")
