"""The network option that reads the humans and the goal in the robot's heading frame (the range scan's frame): the
rotation against vectors computed from the world state by hand, the option's validation, and the option carried
through saving, loading and the exported navigator."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch as th
from pydantic import ValidationError

import socnav
from socnav.export import export_onnx
from socnav.rl import make_model
from socnav.rl.extractor import HumanLSTMExtractor, to_heading_frame
from socnav.rl.persistence import load_policy, save_policy
from socnav.rl.presets import resolve_config
from socnav.runtime import ExportedPolicy
from socnav.sim.observation import observe_robot

DOORWAY = {"scenario": "doorway", "n_humans": 3, "scan": {"beams": 36}, "planner": {"observe": True}}
TINY = {"lstm_hidden_size": 16, "net_arch_pi": (32,), "net_arch_vf": (32,), "n_steps": 32, "batch_size": 32,
        "n_epochs": 1}


def _rotate(vector: np.ndarray, angle: float) -> np.ndarray:
    """`vector` (.., 2) rotated by `angle` (counter-clockwise)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.stack((c * vector[..., 0] - s * vector[..., 1], s * vector[..., 0] + c * vector[..., 1]), axis=-1)


@pytest.mark.parametrize("heading", [0.0, 0.7, -2.9, math.pi])
def test_humans_and_goal_are_rotated_into_the_heading_frame(heading):
    """Each human's offset and relative velocity, and the goal's direction, equal the world-frame vectors rotated by
    minus the robot's heading, computed here without the observation's goal frame."""
    position, velocity, goal = np.array([1.0, -2.0]), np.array([0.3, 0.4]), np.array([-3.0, 5.0])
    human_positions = np.array([[2.0, -1.0], [0.0, 0.5], [-1.5, -3.0]])
    human_velocities = np.array([[-0.5, 0.2], [0.0, 0.0], [1.0, 1.0]])
    observation = observe_robot(position, velocity, heading, goal, 1.0, 0.3, human_positions, human_velocities,
                                np.full(3, 0.3), max_humans=5)
    robot, humans = to_heading_frame(th.as_tensor(observation["robot"], dtype=th.float64),
                                     th.as_tensor(observation["humans"], dtype=th.float64))
    robot, humans = robot.numpy()[0], humans.numpy()[0]
    rows = humans[observation["humans_mask"][0] > 0]
    expected_offsets = _rotate(human_positions - position, -heading)
    expected_velocities = _rotate(human_velocities - velocity, -heading)
    for offset, relative_velocity in zip(expected_offsets, expected_velocities, strict=True):
        match = np.flatnonzero(np.abs(rows[:, :2] - offset).max(axis=1) < 1e-5)
        assert len(match) == 1, f"no row with offset {offset} in {rows[:, :2]}"
        np.testing.assert_allclose(rows[match[0], 2:4], relative_velocity, atol=1e-5)
    np.testing.assert_array_equal(humans[3:], 0.0)  # the padding rows stay zero
    direction = _rotate(goal - position, -heading)
    np.testing.assert_allclose(robot[5:], direction / np.linalg.norm(direction), atol=1e-5)
    np.testing.assert_allclose(robot[:5], observation["robot"][0], atol=1e-7)
    np.testing.assert_allclose(humans[:3, 4:], observation["humans"][0, :3, 4:], atol=1e-7)  # radii and gaps


def test_the_goal_frame_extractor_reads_the_observation_as_it_is():
    """frame='goal' (the paper's) feeds the LSTM the rows unrotated: its features differ from the heading frame's only
    by the rotation (same weights, seeded alike), which is the identity for a robot facing its goal."""
    space = socnav.make_vec_env({"n_humans": 2}, n_envs=1).observation_space
    th.manual_seed(0)
    goal = HumanLSTMExtractor(space, lstm_hidden_size=8)
    th.manual_seed(0)
    heading = HumanLSTMExtractor(space, lstm_hidden_size=8, frame="heading")
    observation = {"robot": th.tensor([[3.0, 0.0, 0.5, 1.0, 0.3]]),
                   "humans": th.tensor([[[1.0, 2.0, -0.5, 0.1, 0.3, 0.6, 1.6]] * 2]),
                   "humans_mask": th.tensor([[1.0, 1.0]])}
    facing = goal(observation)
    assert heading.features_dim == goal.features_dim + 2
    np.testing.assert_allclose(heading(observation)[0, :-2].detach(), facing[0].detach(), atol=1e-6)
    observation["robot"][0, 1] = 1.0  # the robot turned away from its goal: the humans are read elsewhere
    assert (heading(observation)[0, :8] - goal(observation)[0, :8]).abs().max() > 1e-4


def test_an_unknown_frame_is_a_clear_error():
    with pytest.raises(ValidationError, match="frame"):
        resolve_config("odv-ppo-drop", {"frame": "world"})
    space = socnav.make_vec_env({"n_humans": 1}, n_envs=1).observation_space
    with pytest.raises(ValueError, match=r"frame must be one of \['goal', 'heading'\], got 'map'"):
        HumanLSTMExtractor(space, frame="map")


def _option(policy, name: str) -> str:
    extractor = policy.features_extractor
    return extractor.frame if name == "frame" else extractor.scan_encoder.encoding


# the network options read in the network itself: `frame: heading` here, `scan_encoding` (test_scan_encoding.py)
@pytest.mark.parametrize(("name", "value"), [("frame", "heading"), ("scan_encoding", "nearness")])
def test_a_heading_frame_policy_trains_saves_loads_and_exports(tmp_path, name, value):
    """The option travels with the policy's config: the loaded policy and the exported navigator (the rotation or
    the encoding is in the graph) act as the trained one."""
    th.set_num_threads(1)
    env = socnav.make_vec_env(DOORWAY, n_envs=2)
    env.seed(0)
    model = make_model("odv-ppo-drop", env, seed=0, overrides={**TINY, name: value})
    model.learn(64)
    assert _option(model.policy, name) == value
    observations = env.reset()
    for _ in range(5):
        observations = env.step(model.predict(observations, deterministic=True)[0])[0]
    expected, _ = model.policy.predict(observations, deterministic=True)
    metadata = {"algo": "odv-ppo-drop", "algo_config": model.algo_config,
                "env_config": socnav.load_config(DOORWAY).model_dump(mode="json")}
    loaded = load_policy(save_policy(model.policy, tmp_path / "option.zip", metadata))
    assert _option(loaded, name) == value
    np.testing.assert_allclose(loaded.predict(observations, deterministic=True)[0], expected, atol=1e-6)
    network = ExportedPolicy.load(export_onnx(loaded, tmp_path / "option.onnx", k=2, env_config=DOORWAY))
    np.testing.assert_allclose(network.predict(observations)[0], expected, atol=1e-4)
