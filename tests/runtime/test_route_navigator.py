"""The navigator of a policy that observes its route (``planner.observe``): the file is format 5, the navigator plans
the robot's path on the file's walls and hands the policy the goal along it exactly as the simulator does, follows a
path it is given instead, works in a map frame apart from the robot's own, and its fallback heads for the goal."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

import socnav
from socnav.export import export_onnx
from socnav.rl import make_model
from socnav.runtime import ExportedPolicy, InputError, NavigatorLoadError, SafeNavigator
from socnav.runtime.format import CHECKSUM_KEY, METADATA_KEY, ROUTE_VERSION, seal
from socnav.safety import Thresholds
from socnav.safety.cautious import CautiousController

DOORWAY = {"scenario": "doorway", "n_humans": 3, "scan": {"beams": 36}, "planner": {"observe": True}}
TINY = {"lstm_hidden_size": 16, "net_arch_pi": (32,), "net_arch_vf": (32,)}
TOLERANCE = 1e-5
#: A rule that never fires (no gap is below 0): the policy alone drives.
NEVER = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=0.0, beta1=0.0, conditions="proximity-only")
#: A rule that fires whenever a human is observed.
ALWAYS = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=1000.0, beta1=0.0,
                           conditions="proximity-only")
GOAL_DISTANCE, GOAL_HEADING = 0, 1  # socnav.envs.spaces.ROBOT_FEATURE_NAMES


@pytest.fixture(scope="module")
def route_policy():
    torch.set_num_threads(1)
    return make_model("odv-ppo-drop", socnav.make_vec_env(DOORWAY, n_envs=1), seed=2, overrides=TINY).policy


@pytest.fixture(scope="module")
def route_file(route_policy, tmp_path_factory) -> Path:
    return export_onnx(route_policy, tmp_path_factory.mktemp("route") / "doorway.onnx", k=4, env_config=DOORWAY)


def _metadata(path: Path) -> dict:
    model = onnx.load(str(path))
    return json.loads({entry.key: entry.value for entry in model.metadata_props}[METADATA_KEY])


def test_a_route_observing_navigator_is_a_version_5_file(route_file, tmp_path):
    """Version 5, and only for such a policy: a reader that does not plan (socnav up to version 4) refuses it by its
    version; a version-5 file without the route, or a route in a version-3 file, is refused as inconsistent."""
    assert _metadata(route_file)["version"] == ROUTE_VERSION == 5
    assert SafeNavigator.load(route_file, seed=0).route is not None
    model = onnx.load(str(route_file))
    for version, match in ((3, "version 5 is the version of a navigator whose policy observes its route"),):
        metadata = _metadata(route_file)
        metadata["version"] = version
        for entry in model.metadata_props:
            if entry.key == METADATA_KEY:
                entry.value = json.dumps(metadata)
            if entry.key == CHECKSUM_KEY:
                entry.value = "0" * 64
        edited = tmp_path / "edited.onnx"
        edited.write_bytes(seal(model.SerializeToString()))
        with pytest.raises(NavigatorLoadError, match=match):
            ExportedPolicy.load(edited)


def test_the_navigator_observes_the_route_the_simulator_observes(route_policy, route_file, navigator_steps):
    """Driving the doorway from the world's state arrays, the scan and nothing else: at every step the navigator's
    observation (its own path planned on the file's walls) is the environment's, and its action the torch
    policy's (standing still where its wall stop says the step would meet a wall)."""
    from socnav.envs.env import SocialNavEnv

    navigator = SafeNavigator.load(route_file, thresholds=NEVER, seed=0)
    env = SocialNavEnv(socnav.load_config(DOORWAY))
    steps = turned = 0
    for observation, robot, decision in navigator_steps(env, navigator, [40, 41, 42]):
        for key, value in observation.items():
            np.testing.assert_allclose(decision.observation[key][0], value, rtol=0, atol=1e-5, err_msg=key)
        expected, _ = route_policy.predict(observation, deterministic=True)
        if decision.wall_stop:  # the policy's step would have met a wall: the same turn, standing still
            expected = np.array([-1.0, expected[1]], dtype=np.float32)
        np.testing.assert_allclose(decision.action, expected, rtol=0, atol=TOLERANCE)
        bearing_to_goal = math.atan2(*(np.asarray(robot["goal"]) - robot["position"])[::-1])
        bearing_to_subgoal = math.atan2(*(decision.subgoal - robot["position"])[::-1])
        turned += abs(math.remainder(bearing_to_subgoal - bearing_to_goal, math.tau)) > 0.05
        steps += 1
    assert steps > 30 and turned > 0  # the route was not the straight line to the goal at every step


def test_the_observation_does_not_depend_on_the_robots_frame(route_file):
    """The same situation told in the map frame, or in an odometry frame rotated and shifted from it with the map
    pose given: the same observation (robot-centric), the same subgoal in the map frame."""
    navigator = SafeNavigator.load(route_file, thresholds=NEVER, seed=0)
    scan = np.full(36, 8.0)
    # the doorway's wall is x = 0 with its door about y = 0: from the left room to a goal up in the right room
    robot = {"position": [-3.0, 3.0], "velocity": [0.2, 0.0], "heading": 0.3, "goal": [4.0, 3.0], "v_pref": 1.0,
             "radius": 0.3}
    humans = {"positions": [[-1.5, 2.0]], "velocities": [[0.1, 0.0]], "radii": [0.3]}
    in_map = navigator.act(robot, humans, scan=scan)
    angle, shift = 1.1, np.array([20.0, -7.0])
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])

    def odom(point):
        return rotation @ np.asarray(point, dtype=float) + shift

    navigator.reset()
    in_odom = navigator.act({**robot, "position": odom(robot["position"]), "goal": odom(robot["goal"]),
                             "velocity": rotation @ robot["velocity"], "heading": robot["heading"] + angle},
                            {**humans, "positions": [odom(p) for p in humans["positions"]],
                             "velocities": [rotation @ v for v in humans["velocities"]]},
                            scan=scan, pose=[*robot["position"], robot["heading"]])
    np.testing.assert_allclose(in_odom.subgoal, in_map.subgoal, atol=1e-9)
    for key in in_map.observation:
        np.testing.assert_allclose(in_odom.observation[key], in_map.observation[key], atol=1e-5, err_msg=key)
    assert abs(in_map.observation["robot"][0, GOAL_HEADING]) > 0.1  # the door, not the goal, is ahead


def test_a_given_path_is_followed_by_pure_pursuit(route_file):
    """A nav_msgs/Path's waypoints replace the navigator's own path: the subgoal lies `lookahead` (1 m) along the
    path beyond its point nearest to the robot, and the observed goal keeps the goal's distance (hand-computed)."""
    navigator = SafeNavigator.load(route_file, thresholds=NEVER, seed=0)
    robot = {"position": [-3.0, 1.0], "velocity": [0.0, 0.0], "heading": 0.0, "goal": [-3.0, 5.0], "v_pref": 1.0,
             "radius": 0.3}
    decision = navigator.act(robot, None, scan=np.full(36, 8.0), path=[[-3.0, 0.0], [3.0, 0.0], [3.0, 3.5]])
    np.testing.assert_allclose(decision.subgoal, [-2.0, 0.0])  # nearest (-3, 0), then 1 m along +x
    assert decision.observation["robot"][0, GOAL_DISTANCE] == pytest.approx(4.0, rel=1e-6)
    # heading 0 relative to the observed goal's direction, which points at the subgoal: -(-45 degrees)
    assert decision.observation["robot"][0, GOAL_HEADING] == pytest.approx(math.pi / 4, abs=1e-6)
    near_the_end = navigator.act({**robot, "position": [3.2, 3.3]}, None, scan=np.full(36, 8.0),
                                 path=[[-3.0, 0.0], [3.0, 0.0], [3.0, 3.5]])
    np.testing.assert_allclose(near_the_end.subgoal, [3.0, 3.5])  # the last waypoint at most


@pytest.mark.parametrize("path,match", [
    ("a path", "path: expected a list of"),
    ([[0.0, 1.0, 2.0]], r"path: expected shape \(M, 2\)"),
    ([], r"path: expected shape \(M, 2\) with M >= 1"),
    ([[0.0, 0.0], [np.nan, 1.0]], "path: waypoint 1 is not finite"),
])
def test_a_bad_path_is_a_clear_error(route_file, path, match):
    navigator = SafeNavigator.load(route_file, seed=0)
    robot = {"position": [-3.0, 1.0], "velocity": [0.0, 0.0], "heading": 0.0, "goal": [3.0, 1.0], "v_pref": 1.0,
             "radius": 0.3}
    with pytest.raises(InputError, match=match):
        navigator.act(robot, None, scan=np.full(36, 8.0), path=path)


def test_a_path_is_refused_by_a_policy_that_does_not_observe_a_route(tmp_path):
    config = {"scenario": "circle_crossing", "n_humans": 2}
    model = make_model("ppo-drop", socnav.make_vec_env(config, n_envs=1), seed=1, overrides=TINY)
    navigator = SafeNavigator.load(export_onnx(model.policy, tmp_path / "open.onnx", k=2, env_config=config), seed=0)
    robot = {"position": [0.0, 0.0], "velocity": [0.0, 0.0], "heading": 0.0, "goal": [3.0, 0.0], "v_pref": 1.0,
             "radius": 0.3}
    with pytest.raises(InputError, match="path: this navigator's policy does not observe a route"):
        navigator.act(robot, None, path=[[0.0, 0.0], [3.0, 0.0]])


def test_the_fallback_acts_on_the_policys_observation_of_its_route(route_file):
    """As in the simulator's safety layer (`SafePolicy` hands its fallback the env's observation): the cautious
    fallback sees the goal along the route, as the policy does, so a robot it holds at rest faces the subgoal and
    not the goal behind the wall (the simulator's layer and this navigator decided apart there)."""
    navigator = SafeNavigator.load(route_file, thresholds=ALWAYS, seed=0)
    config = socnav.load_config(DOORWAY)
    robot = {"position": [-3.0, 3.0], "velocity": [0.0, 0.0], "heading": 0.0, "goal": [4.0, 3.0], "v_pref": 1.0,
             "radius": 0.3}
    humans = {"positions": [[-4.5, 1.0]], "velocities": [[0.0, 0.0]], "radii": [0.3]}
    handed = []
    predict = navigator.cautious.predict
    navigator.cautious.predict = lambda observation: handed.append(observation) or predict(observation)
    decision = navigator.act(robot, humans, scan=np.full(36, 8.0))
    assert decision.fallback and len(handed) == 1
    for key, value in decision.observation.items():
        np.testing.assert_array_equal(handed[-1][key], value, err_msg=key)
    plain = SafeNavigator.load(route_file, thresholds=ALWAYS, seed=0)
    plain.route = None  # the same navigator without the route: it observes the goal itself
    real_goal = plain.act(robot, humans, scan=np.full(36, 8.0)).observation
    assert abs(real_goal["robot"][0, GOAL_HEADING] - decision.observation["robot"][0, GOAL_HEADING]) > 0.1
    expected = CautiousController(config).predict(decision.observation)[0][0]
    np.testing.assert_allclose(decision.action, expected, atol=1e-6)


def test_a_map_that_arrives_later_replaces_the_walls(route_file):
    """`set_walls` (a nav_msgs/OccupancyGrid that arrives): no walls, then the doorway's again, decides as the file's
    own map; invalid walls are refused and leave the map as it was."""
    robot = {"position": [-3.0, 3.0], "velocity": [0.0, 0.0], "heading": 0.0, "goal": [4.0, 3.0], "v_pref": 1.0,
             "radius": 0.3}
    scan = np.full(36, 8.0)
    navigator = SafeNavigator.load(route_file, thresholds=NEVER, seed=0)
    walls = [wall.copy() for wall in navigator.walls]
    with_file_map = navigator.act(robot, None, scan=scan)
    navigator.set_walls([])
    assert navigator.walls is None and navigator.route is None
    navigator.reset()
    open_plane = navigator.act(robot, None, scan=scan)
    assert open_plane.subgoal is None and open_plane.observation["robot"][0, GOAL_HEADING] == pytest.approx(0.0)
    navigator.set_walls(walls)
    navigator.reset()
    again = navigator.act(robot, None, scan=scan)
    np.testing.assert_array_equal(again.subgoal, with_file_map.subgoal)
    np.testing.assert_array_equal(again.action, with_file_map.action)
    with pytest.raises(ValueError, match=r"walls\[0\]: a polygon needs at least 2 vertices"):
        navigator.set_walls([[[0.0, 0.0]]])
    assert navigator.route is not None and len(navigator.walls) == len(walls)
