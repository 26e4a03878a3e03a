"""Attention (docs/attention.md): inattentive humans and the human field of view, on hand-built scenes and in
bulk."""

import math

import numpy as np
import pytest
from scipy import stats

from socnav.config import load_config
from socnav.controllers import OrcaController
from socnav.envs.rollout import rollout_episodes
from socnav.sim.scenarios import InitialState
from socnav.sim.world import CrowdWorld


def _stage(config, robot, robot_goal, human, human_goal, human_speed=1.0):
    """One environment: a robot and one human (cooperation 0.5, personal space 0.3), both at rest."""
    world = CrowdWorld(config, 1)
    state = InitialState.empty(1, world.n_slots)
    state.positions[0, 0], state.goals[0, 0] = robot, robot_goal
    state.positions[0, 1], state.goals[0, 1] = human, human_goal
    state.radii[0, :2] = 0.3
    state.preferred_speeds[0, :2] = (1.0, human_speed)
    state.personal_space_radii[0, 1] = 0.3
    state.cooperation[0, 1] = 0.5
    state.active[0, :2] = True
    state.robot_heading[0] = 0.0
    world.load(0, state)
    return world


def _walk(world, attentive, steps, robot_action=(-1.0, 0.0)):
    """Set the human's attention and step; the default action keeps the robot standing still."""
    world.set_attention(0, np.array([True, attentive] + [True] * (world.n_slots - 2)))
    path = []
    for _ in range(steps):
        world.step(np.array([robot_action]))
        path.append(world.positions[0, 1].copy())
    return np.array(path), world.min_gap[0]


def test_inattentive_human_walks_straight_through_the_robot():
    config = load_config({"scenario": "position_swap", "human_fov_deg": 360})
    # Slightly off the robot's centre: an exactly head-on ORCA encounter with a static disc only slows down.
    scene = dict(robot=(0.0, 0.0), robot_goal=(0.0, 5.0), human=(-4.0, 0.05), human_goal=(4.0, 0.05))
    blind_path, blind_gap = _walk(_stage(config, **scene), attentive=False, steps=20)
    seen_path, seen_gap = _walk(_stage(config, **scene), attentive=True, steps=20)
    # Inattentive: the straight line to its goal, through where the robot stands (a collision, gap < 0).
    np.testing.assert_allclose(blind_path[:, 1], 0.05, atol=1e-12)
    assert blind_gap < 0.0
    # Attentive: it steps aside and keeps clear of the robot's body.
    assert np.abs(seen_path[:, 1] - 0.05).max() > 0.3
    assert seen_gap > 0.0


def test_human_reacts_only_once_the_robot_enters_its_view():
    """A human walking away from the robot does not react to it behind its back, then does once it is in view."""
    config = load_config({"scenario": "position_swap", "human_fov_deg": 200})
    world = _stage(config, robot=(-1.5, 0.0), robot_goal=(10.0, 0.0), human=(0.0, 0.0), human_goal=(10.0, 0.0),
                   human_speed=0.5)
    world.set_attention(0, np.array([True, True] + [True] * (world.n_slots - 2)))
    invisible = _stage(load_config({"scenario": "position_swap", "robot_visible": False}), robot=(-1.5, 0.0),
                       robot_goal=(10.0, 0.0), human=(0.0, 0.0), human_goal=(10.0, 0.0), human_speed=0.5)
    # The robot closes in from behind (it is faster): the human walks on exactly as if the robot were not there.
    for _ in range(3):
        world.step(np.array([[1.0, 0.0]]))
        invisible.step(np.array([[1.0, 0.0]]))
        assert not world.noticed[0, 1]
        np.testing.assert_array_equal(world.positions[0, 1], invisible.positions[0, 1])
    # Put the robot in front of the human, within its cone: it notices and changes its velocity.
    world.positions[0, 0] = world.positions[0, 1] + (1.2, 0.2)
    world.velocities[0, 0] = 0.0
    world.step(np.array([[-1.0, 0.0]]))
    assert world.noticed[0, 1]
    assert abs(world.velocities[0, 1, 1]) > 1e-3, "an attentive human that sees the robot plans around it"
    # Behind its back again but within the interaction range: it keeps reacting.
    world.positions[0, 0] = world.positions[0, 1] - (2.0, 0.0)
    world.step(np.array([[-1.0, 0.0]]))
    assert world.noticed[0, 1] and world.sees[0, 1, 0]
    # Beyond the interaction range (ORCA neighbour distance) and behind: forgotten.
    world.positions[0, 0] = world.positions[0, 1] - (config.orca.neighbor_dist + 1.0, 0.0)
    world.step(np.array([[-1.0, 0.0]]))
    assert not world.noticed[0, 1] and not world.sees[0, 1, 0]


def test_view_cone_boundary_by_hand():
    """fov 200 deg: half-angle 100 deg from the walking direction; 95 deg is seen, 105 deg is not."""
    config = load_config({"scenario": "position_swap", "human_fov_deg": 200})
    for angle, seen in ((95.0, True), (105.0, False)):
        offset = 3.0 * np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
        world = _stage(config, robot=tuple(offset), robot_goal=tuple(offset + 5.0), human=(0.0, 0.0),
                       human_goal=(8.0, 0.0))
        world.set_attention(0, np.ones(world.n_slots, dtype=bool))
        world.step(np.array([[-1.0, 0.0]]))  # standing still, the human faces its goal (+x)
        assert bool(world.noticed[0, 1]) is seen, angle


@pytest.mark.parametrize("share", [0.0, 0.3, 1.0])
def test_inattentive_share_matches_the_configured_probability(share):
    config = load_config({"scenario": "circle_crossing", "n_humans": 5, "inattentive_share": share})
    world = CrowdWorld(config, 400)
    for env in range(400):
        world.seed(env, 10_000 + env)
    world.reset()
    humans = world.active & world.humans_slots
    inattentive = int((~world.attentive & humans).sum())
    total = int(humans.sum())
    assert total == 2000
    if share in (0.0, 1.0):
        assert inattentive == round(share * total)
    else:  # two-sided exact binomial test at the 0.1 % level
        assert stats.binomtest(inattentive, total, share).pvalue > 1e-3
    assert world.attentive[:, 0].all(), "slot 0 is the robot"


def test_observation_does_not_depend_on_attentiveness():
    config = load_config({"scenario": "circle_crossing", "inattentive_share": 0.5})
    world = CrowdWorld(config, 3)
    for env in range(3):
        world.seed(env, env)
    world.reset()
    for _ in range(12):
        world.step(np.zeros((3, 2)))
    before = world.observe()
    for env in range(3):
        world.set_attention(env, ~world.attentive[env])
    after = world.observe()
    for key in before:
        np.testing.assert_array_equal(before[key], after[key])


def test_attention_leaves_the_rest_of_the_episode_unchanged():
    """Attentiveness comes from the counter-based key: starts, goals, speeds, spaces are those of the old world."""
    worlds = [CrowdWorld(load_config({"scenario": "random", "inattentive_share": s, "human_fov_deg": f}), 2)
              for s, f in ((0.0, 360.0), (0.6, 120.0))]
    for world in worlds:
        world.seed(0, 5)
        world.seed(1, 6)
        world.reset()
    for name in ("positions", "goals", "preferred_speeds", "personal_space", "cooperation", "heading", "noise_keys"):
        np.testing.assert_array_equal(getattr(worlds[0], name), getattr(worlds[1], name))


def test_records_with_attention_do_not_depend_on_batch_size():
    config = load_config({"scenario": "circle_interaction", "inattentive_share": 0.5, "human_fov_deg": 150})
    policy = OrcaController(config)
    one = rollout_episodes(policy, config, 6, seed=90, n_envs=1)
    many = rollout_episodes(policy, config, 6, seed=90, n_envs=5)
    np.testing.assert_array_equal(one.drop(columns=["outcome"]).to_numpy(dtype=float),
                                  many.drop(columns=["outcome"]).to_numpy(dtype=float))


def test_speed_noise_above_one_is_clipped_to_one():
    config = load_config({"scenario": "position_swap", "perturbation": {"speed_noise": 2.0}})
    assert config.perturbation.speed_noise == 1.0
    world = CrowdWorld(config, 1)
    world.seed(0, 0)
    world.reset()
    for _ in range(20):
        world.step(np.array([[1.0, 0.0]]))
        speed = np.linalg.norm(world.velocities[0, 0])
        assert 0.0 <= speed <= world.preferred_speeds[0, 0] + 1e-12
