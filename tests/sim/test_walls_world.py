"""Walls in the world: the map scenarios, wall collisions, occlusion, the range scan, the ORCA robot among walls,
and config validation. The kernels themselves are tested against pyrvo (test_obstacles.py) and shapely
(test_geometry.py, test_maps.py); here the world is checked on staged scenes with hand-computed answers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import socnav
from socnav.config import ConfigError, load_config
from socnav.controllers import make_controller
from socnav.envs.rollout import rollout_episodes
from socnav.sim.geometry import distance_to_segments
from socnav.sim.scenarios import InitialState, get_scenario
from socnav.sim.world import OUTCOME_COLLISION_WALL, OUTCOME_RUNNING, CrowdWorld

MAP_SCENARIOS = ("corridor", "doorway", "intersection", "room")


def staged(config: dict, robot: tuple, heading: float, goal: tuple, humans: list[tuple] = ()) -> CrowdWorld:
    """A one-environment world loaded with the robot at `robot` facing `heading`, and standing humans."""
    world = CrowdWorld(load_config({"n_humans": len(humans), **config}), 1)
    state = InitialState.empty(1, world.n_slots)
    state.active[0, : 1 + len(humans)] = True
    state.positions[0, 0], state.goals[0, 0], state.robot_heading[0] = robot, goal, heading
    state.radii[0, : 1 + len(humans)] = 0.3
    state.preferred_speeds[0, : 1 + len(humans)] = 1.0
    for k, position in enumerate(humans, start=1):
        state.positions[0, k] = state.goals[0, k] = position
    world.load(0, state)
    return world


@pytest.mark.parametrize("scenario", MAP_SCENARIOS)
def test_map_scenarios_pass_the_checkers_and_start_clear_of_the_walls(scenario):
    env = socnav.make_env({"scenario": scenario, "scan": {"beams": 18}})
    check_env(env, skip_render_check=True)
    sb3_check_env(env, warn=False)
    world = CrowdWorld(load_config({"scenario": scenario}), 8)
    for env_index in range(8):
        world.seed(env_index, env_index)
    world.reset()
    active = world.active
    points = np.concatenate([world.positions[active], world.goals[active]])
    radii = np.concatenate([world.radii[active]] * 2)
    assert world.walls.misplaced(points, radii) is None


@pytest.mark.parametrize("scenario", MAP_SCENARIOS)
def test_orca_humans_never_cross_a_wall(scenario):
    world = CrowdWorld(load_config({"scenario": scenario}), 4)
    for env in range(4):
        world.seed(env, 100 + env)
    world.reset()
    walls = world.walls
    for _ in range(80):
        before = world.positions.copy()
        world.step(np.zeros((4, 2)))
        for env in range(4):
            for human in np.flatnonzero(world.active[env, 1:]) + 1:
                # the straight move of this step crosses no wall segment, and ends outside the walls' reach
                gap = distance_to_segments(world.positions[env, human][None], walls.seg_start[:1], walls.seg_end[:1],
                                           walls.n_segments[:1])[0] - world.radii[env, human]
                assert gap > -0.05, (scenario, env, human, gap)
                assert not walls.robot_hit(before[env, human][None], world.positions[env, human][None],
                                           np.zeros(1))[0]
        world.reset(np.flatnonzero(world.time > 30.0))


def test_driving_into_a_wall_ends_the_episode_with_its_own_outcome_and_the_collision_penalty():
    # corridor walls at y = +-1.5; the robot 0.5 m below the top wall, facing it, drives at full speed (1 m/s)
    world = staged({"scenario": "corridor"}, robot=(0.0, 0.7), heading=math.pi / 2, goal=(6.0, 0.0))
    outcomes, rewards = [], []
    for _ in range(3):
        result = world.step(np.array([[1.0, 0.0]]))
        outcomes.append(int(result.outcome[0]))
        rewards.append(float(result.reward[0]))
        if result.terminated[0]:
            break
    # step 1: 0.25 m up, centre at y = 0.95, gap 1.5 - 0.95 - 0.3 = 0.25: running; step 2: gap 0 at y = 1.2 ...
    # the disc reaches the wall during step 3 (centre 1.2 -> 1.45, radius 0.3, wall at 1.5)
    assert outcomes[:-1] == [OUTCOME_RUNNING] * (len(outcomes) - 1)
    assert outcomes[-1] == OUTCOME_COLLISION_WALL and len(outcomes) == 3
    cfg = world.config.reward
    progress = math.hypot(6.0, 1.2) - math.hypot(6.0, 1.45)  # d_goal(t-1) - d_goal(t), the goal is at (6, 0)
    assert rewards[-1] == pytest.approx(-cfg.time * 0.25 + cfg.progress * progress - cfg.collision)
    assert world.wall_collision[0]
    assert world.episode_summary(0, outcomes[-1])["outcome"] == "collision_wall"


def test_a_human_behind_a_corner_is_hidden_and_does_not_notice_the_robot():
    # intersection (arms 3 m wide, corner blocks from 1.5 m): robot in the south arm, one human in the west arm
    # behind the south-west block, one straight ahead in the north arm
    config = {"scenario": "intersection", "human_fov_deg": 360.0, "inattentive_share": 0.0}
    world = staged(config, robot=(0.0, -4.0), heading=math.pi / 2, goal=(0.0, 7.0),
                   humans=[(-4.0, 0.0), (0.0, 4.0)])
    observation = world.observe()
    assert observation["humans_mask"][0].sum() == 1.0  # only the human in the north arm
    assert observation["humans"][0, 0, 0] == pytest.approx(8.0, abs=1e-5)  # 8 m ahead in the goal frame
    world.step(np.array([[-1.0, 0.0]]))  # the robot stands still
    assert not world.sees[0, 1, 0] and world.sees[0, 2, 0]
    visible = staged({**config, "occlusion": False}, robot=(0.0, -4.0), heading=math.pi / 2, goal=(0.0, 7.0),
                     humans=[(-4.0, 0.0), (0.0, 4.0)])
    assert visible.observe()["humans_mask"][0].sum() == 2.0  # occlusion off: both observed, as in the open plane


def test_the_scan_reads_the_distance_to_each_wall():
    # corridor (3 m wide, 16 m long): at the centre facing +x, the beams at +-90 degrees hit the walls 1.5 m away;
    # the beam along the corridor leaves through the open end (max range)
    config = {"scenario": "corridor", "scan": {"beams": 4, "range": 5.0, "fov": 360.0}}
    world = staged(config, robot=(0.0, 0.0), heading=0.0, goal=(6.0, 0.0))
    scan = world.observe()["scan"][0]
    # LaserScan order from -180 degrees counter-clockwise in 90-degree steps: behind, right, ahead, left
    assert scan == pytest.approx([5.0, 1.5, 5.0, 1.5], abs=1e-6)
    assert world.observe()["pose"][0] == pytest.approx([0.0, 0.0, 0.0])


def test_worlds_without_walls_observe_what_they_did():
    world = CrowdWorld(load_config({"scenario": "circle_crossing"}), 2)
    world.reset()
    assert set(world.observe()) == {"robot", "humans", "humans_mask"}
    assert world.walls is None and not world.occlusion
    dumped = load_config({}).model_dump()
    assert not {"obstacles", "map", "occlusion", "scan", "layout"} & set(dumped)
    assert "time_horizon_obst" not in dumped["orca"]


@pytest.mark.parametrize("scenario", ["corridor", "doorway", "intersection"])
def test_the_orca_robot_crosses_an_empty_map_and_straight_does_not_hit_its_walls(scenario):
    config = load_config({"scenario": scenario, "n_humans": 0})
    records = rollout_episodes(make_controller("orca", config), config, 20, seed=0, n_envs=10)
    assert (records["outcome"] == "goal").all()


def test_obstacles_in_an_open_scenario_are_avoided_and_starts_redrawn_clear_of_them():
    # a pillar across the robot's paths of circle crossing (the axes), off their centre lines: the ORCA robot goes
    # around it (a pillar centred on a path is ORCA's local minimum, which the global planner gets round: test_planning)
    pillar = [[0.2, 0.2], [1.0, 0.2], [1.0, 1.0], [0.2, 1.0]]
    config = load_config({"scenario": "circle_crossing", "n_humans": 0, "obstacles": [pillar]})
    records = rollout_episodes(make_controller("orca", config), config, 8, seed=0, n_envs=8)
    assert (records["outcome"] == "goal").all()
    straight = rollout_episodes(make_controller("straight", config), config, 8, seed=0, n_envs=8)
    assert (straight["outcome"] == "collision_wall").sum() >= 6  # it turns towards the goal from a random heading


def test_an_obstacle_over_every_start_is_a_clear_error():
    cover = [[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]
    with pytest.raises(ConfigError, match="clear of the walls"):
        CrowdWorld(load_config({"scenario": "circle_crossing", "obstacles": [cover]}), 1).reset()


def test_bad_maps_are_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"obstacles\[0\]: self-intersecting"):
        load_config({"obstacles": [[[0, 0], [1, 1], [1, 0], [0, 1]]]})
    with pytest.raises(ConfigError, match="map file not found"):
        load_config({"map": "/nonexistent/map.yaml"})
    with pytest.raises(ConfigError, match="scan"):
        load_config({"scan": {"beams": 0}})


def test_routes_of_the_doorway_go_through_the_door():
    scenario, config = get_scenario("doorway"), load_config({"scenario": "doorway"})
    rng = np.random.default_rng(0)
    goal = np.array([-scenario.approach, 0.0])  # in front of the door, from the left room
    route = []
    for _ in range(4):
        goal = scenario.next_goal(rng, config, goal)
        route.append(goal)
    assert route[0] == pytest.approx([scenario.exit, 0.0])  # through the door
    assert route[1][0] > scenario.exit  # into the right room
    assert route[2] == pytest.approx([scenario.approach, 0.0])  # back to the door from the right
    assert route[3] == pytest.approx([-scenario.exit, 0.0])


@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_placement_check_agrees_with_the_shapely_rule(seed):
    from socnav.sim.geometry import discs_clear
    from socnav.sim.maps import clearance_violation
    from socnav.sim.walls import Walls

    rng = np.random.default_rng(seed)
    room = [[-6.0, -6.0], [-6.0, 6.0], [6.0, 6.0], [6.0, -6.0]]  # clockwise: free space inside
    pillar = [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]  # counter-clockwise: solid
    wall = [[2.0, -3.0], [2.0, 3.0]]
    polygons = [np.array(p, dtype=float) for p in (room, pillar, wall)][: 1 + seed % 3]
    walls = Walls(polygons, 1)
    points, radii = rng.uniform(-8.0, 8.0, (60, 2)), rng.uniform(0.1, 0.6, 60)
    for point, radius in zip(points, radii, strict=True):
        fits = clearance_violation(polygons, point, radius, name="walls") is None
        assert discs_clear(point[None], np.array([radius]), walls.seg_start[0], walls.seg_end[0],
                           int(walls.n_segments[0]), walls._closed_vertices, walls._closed_offsets,
                           walls._area_sizes, walls._solid_inside, walls._solid_outside) == fits
        assert (walls.misplaced(point[None], np.array([radius])) is None) == fits
