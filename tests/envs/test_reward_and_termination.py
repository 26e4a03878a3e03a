"""Reward terms and episode ends against hand-computed values on staged situations."""

import math

import numpy as np
import pytest

from socnav.config import load_config
from socnav.sim.orca import orca_velocities
from socnav.sim.scenarios import InitialState
from socnav.sim.world import OUTCOME_COLLISION, OUTCOME_GOAL, OUTCOME_TIMEOUT, CrowdWorld


def staged_world(robot, robot_goal, humans=(), reward=None, **config):
    """One environment: robot at `robot` heading to `robot_goal`; humans as (position, goal, r_prox, cooperation)
    or (position, goal, r_prox, cooperation, v_pref); v_pref is 1 m/s for the robot and by default for humans."""
    # Staged humans are attentive and see all around (attention is tested in tests/sim/test_attention.py).
    cfg = load_config({"scenario": "circle_crossing", "n_humans": max(len(humans), 0), "reward": reward or {},
                       "human_fov_deg": 360, **config})
    world = CrowdWorld(cfg, 1)
    state = InitialState.empty(1, world.n_slots)
    state.positions[0, 0], state.goals[0, 0] = robot, robot_goal
    state.radii[0, 0], state.preferred_speeds[0, 0], state.active[0, 0] = 0.3, 1.0, True
    for k, (position, goal, personal_space, cooperation, *v_pref) in enumerate(humans, start=1):
        state.positions[0, k], state.goals[0, k] = position, goal
        state.radii[0, k], state.preferred_speeds[0, k], state.active[0, k] = 0.3, (v_pref or [1.0])[0], True
        state.personal_space_radii[0, k], state.cooperation[0, k] = personal_space, cooperation
    offset = np.subtract(robot_goal, robot)
    state.robot_heading[0] = math.atan2(offset[1], offset[0])
    world.load(0, state)
    return world


NO_SOCIAL = {"personal_space": 0.0, "disturbance": 0.0}


def test_time_and_progress_terms():
    world = staged_world((0.0, 0.0), (10.0, 0.0), reward={**NO_SOCIAL, "time": 0.5, "progress": 2.0})
    result = world.step(np.array([[1.0, 0.0]]))  # full speed 1 m/s straight at the goal for 0.25 s
    assert result.reward[0] == pytest.approx(-0.5 * 0.25 + 2.0 * 0.25)
    assert world.positions[0, 0] == pytest.approx([0.25, 0.0])


def test_speed_and_turn_mapping():
    world = staged_world((0.0, 0.0), (10.0, 0.0), reward=NO_SOCIAL)
    world.step(np.array([[0.0, 1.0]]))  # half speed, full left turn of pi/6
    heading = math.pi / 6
    assert world.heading[0] == pytest.approx(heading)
    assert world.positions[0, 0] == pytest.approx([0.5 * 0.25 * math.cos(heading), 0.5 * 0.25 * math.sin(heading)])
    world.step(np.array([[5.0, -7.0]]))  # out-of-range actions are clipped: full speed, full right turn
    assert world.heading[0] == pytest.approx(0.0)


def test_personal_space_term_hand_computed():
    # A human standing on its goal 0.5 m (gap) ahead of a robot that stands still; its personal space is 0.8 m.
    gap, personal_space = 0.5, 0.8
    human = (1.1, 0.0)  # centre distance 1.1 = gap 0.5 + radii 0.6
    world = staged_world((0.0, 0.0), (0.0, 5.0), [(human, human, personal_space, 0.5)],
                         reward={"time": 0.0, "progress": 0.0, "disturbance": 0.0, "personal_space": 2.0},
                         robot_visible=False)
    result = world.step(np.array([[-1.0, 0.0]]))
    assert result.reward[0] == pytest.approx(-2.0 * (1.0 - gap / personal_space))
    assert result.intrusions[0] == 1 and world.intrusion_events[0] == 1
    world.step(np.array([[-1.0, 0.0]]))
    assert world.intrusion_events[0] == 1, "staying inside is one event"
    assert world.intrusion_steps[0] == 2


def test_disturbance_term_equals_orca_with_and_without_robot():
    # A human walking across the robot's path; the term is |v_with_robot - v_without| / v_pref.
    world = staged_world((0.0, 0.0), (0.0, 6.0), [((2.0, 0.5), (-6.0, 0.5), 0.4, 0.5)],
                         reward={"time": 0.0, "progress": 0.0, "personal_space": 0.0, "disturbance": 1.0})
    w = world
    preferred = np.zeros((1, w.n_slots, 2))
    preferred[0, 1] = [-1.0, 0.0]
    compute = np.array([[False, True]])
    args = (w.positions, w.velocities, w.radii, preferred, w.max_speeds, w.active, compute, w.radius_pad,
            w.avoidance_share)
    orca = (5.0, 10.0, 10, 0.25)
    with_robot = orca_velocities(*args, w.sees, *orca)[0, 1]
    sees = w.sees.copy()
    sees[0, 1, 0] = False
    without = orca_velocities(*args, sees, *orca)[0, 1]
    expected = -np.linalg.norm(with_robot - without) / 1.0
    assert abs(expected) > 1e-3, "the staged robot must actually disturb the human"
    result = world.step(np.array([[-1.0, 0.0]]))
    assert result.reward[0] == pytest.approx(expected)


def test_disturbance_is_relative_to_the_humans_preferred_speed_hand_computed():
    # Head-on, everything at rest: a human (v_pref 0.5 m/s, cooperation c = 0.5) walks straight at a robot that
    # stands still, centres d = 2 m apart. The human sees the robot bigger by its personal space:
    # R = 0.3 + 0.3 + 0.4 = 1 m. RVO2 with both velocities zero: u = (d - R) / tau along the axis (tau = 5 s), the
    # human may close in at no more than c (d - R) / tau = 0.1 m/s; without the robot it walks at its 0.5 m/s.
    # Disturbance (docs/world.md): |v_i - v_i^0| / v_pref,i = (0.5 - 0.1) / 0.5 = 0.8 (0.4 if not divided by v_pref).
    weight = 2.0
    world = staged_world((0.0, 0.0), (0.0, 6.0), [((2.0, 0.0), (-6.0, 0.0), 0.4, 0.5, 0.5)],
                         reward={"time": 0.0, "progress": 0.0, "personal_space": 0.0, "disturbance": weight})
    result = world.step(np.array([[-1.0, 0.0]]))  # speed 0: the robot stays put
    assert world.velocities[0, 1] == pytest.approx([-0.1, 0.0], abs=1e-12), "the hand computation's ORCA velocity"
    assert world.disturbance[0] == pytest.approx(0.8, rel=1e-12)
    assert result.reward[0] == pytest.approx(-weight * 0.8, rel=1e-12)


def test_min_gap_includes_the_closest_approach_between_two_steps():
    # A human walks past a robot that stands still, 1 m to its side, at 1 m/s (it ignores the robot): in the 0.25 s
    # step from x = 0.125 to x = -0.125 it is closest at x = 0, mid-step. Gap there: 1 - 0.6 = 0.4 m; at both
    # ends of the step: sqrt(0.125^2 + 1) - 0.6 = 0.4078 m.
    world = staged_world((0.0, 0.0), (0.0, -9.0), [((0.125, 1.0), (-10.0, 1.0), 0.3, 0.5)], robot_visible=False,
                         reward=NO_SOCIAL)
    result = world.step(np.array([[-1.0, 0.0]]))
    assert world.positions[0, 1] == pytest.approx([-0.125, 1.0], abs=1e-12)
    assert result.nearest_gap[0] == pytest.approx(math.hypot(0.125, 1.0) - 0.6, abs=1e-12)
    assert world.min_gap[0] == pytest.approx(0.4, abs=1e-12)
    assert world.episode_summary(0, int(result.outcome[0]))["min_gap"] == pytest.approx(0.4, abs=1e-12)


def test_goal_collision_and_timeout():
    world = staged_world((0.0, 0.0), (0.2, 0.0), reward={"goal": 7.0, **NO_SOCIAL, "time": 0.0, "progress": 0.0})
    result = world.step(np.array([[-1.0, 0.0]]))
    assert result.outcome[0] == OUTCOME_GOAL and result.terminated[0] and result.reward[0] == pytest.approx(7.0)

    # Humans walking straight into a robot that stands still; humans ignore the robot.
    world = staged_world((0.0, 0.0), (0.0, 9.0), [((1.0, 0.0), (-5.0, 0.0), 0.3, 0.5)], robot_visible=False,
                         reward={"collision": 4.0, **NO_SOCIAL, "time": 0.0, "progress": 0.0})
    outcomes = [world.step(np.array([[-1.0, 0.0]])) for _ in range(3)]
    first = next(r for r in outcomes if r.outcome[0])
    assert first.outcome[0] == OUTCOME_COLLISION and first.reward[0] == pytest.approx(-4.0)

    # Time limit = 2 * |start - goal| / v_pref + margin = 2 * 2 / 1 + 1 = 5 s: standing still ends after 21 steps.
    world = staged_world((0.0, 0.0), (2.0, 0.0), timeout_margin=1.0, reward=NO_SOCIAL)
    ends = [int(world.step(np.array([[-1.0, 0.0]])).outcome[0]) for _ in range(21)]
    assert ends[:20] == [0] * 20 and ends[20] == OUTCOME_TIMEOUT


def test_fast_pass_through_is_a_collision():
    # A human so fast that it jumps across the robot within one step is still a collision (closest approach).
    world = staged_world((0.0, 0.0), (0.0, 9.0), [((2.0, 0.0), (-40.0, 0.0), 0.3, 0.5)], robot_visible=False,
                         perturbation={"human_speed_factor": 16.0}, reward=NO_SOCIAL)
    result = world.step(np.array([[-1.0, 0.0]]))
    assert world.positions[0, 1, 0] < -1.0, "the human ended the step beyond the robot"
    assert result.outcome[0] == OUTCOME_COLLISION
