"""The human-model plug point: the registry and its config field, both models in the env, and ORCA behind the
`HumanModel` protocol replaying recorded episodes bit for bit.

`tests/sim/data/orca_golden.npz` holds seeded episodes (world positions and velocities every step, observations,
rewards, episode ends), recorded once and kept (`python tests/sim/test_human_models.py --record` rewrites it);
`test_default_config_replays_the_recording_bit_for_bit` plays them again and compares with `np.array_equal`. The
social force model's oracle tests are in test_social_force.py.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import socnav
import socnav.sim.humans as humans_registry
from socnav.config import ConfigError, describe_world, load_config
from socnav.sim.humans import (
    Crowd,
    HumanModel,
    OrcaHumans,
    SocialForceHumans,
    human_model_names,
    make_human_model,
    register_human_model,
)
from socnav.sim.scenarios import InitialState
from socnav.sim.world import CrowdWorld

GOLDEN = Path(__file__).parent / "data" / "orca_golden.npz"
MAX_STEPS = 60  # per episode: enough for goals, collisions and redrawn goals, small enough for a < 200 KB file

#: name -> (config, seeds of the env's episodes); the last case steps a batched `CrowdWorld` instead.
ENV_CASES = {
    "circle_crossing": ({"scenario": "circle_crossing"}, (0, 1)),
    "position_swap": ({"scenario": "position_swap"}, (2,)),
    "circle_interaction": ({"scenario": "circle_interaction"}, (3,)),
    "random": ({"scenario": "random"}, (4,)),
    "perturbed": ({"scenario": "circle_crossing", "n_humans": 8, "human_fov_deg": 360, "inattentive_share": 0.5,
                   "perturbation": {"observation_noise": 0.1, "heading_noise": 0.2, "speed_noise": 0.2}}, (5,)),
}
BATCH_CASE = ({"scenario": "random", "reward": {"disturbance": 1.0, "social_radius": 5.0}}, 3, 7)  # config, E, seed


def _action(rng: np.random.Generator, robot_observation: np.ndarray) -> np.ndarray:
    """Roughly towards the goal at a random speed: episodes end by goal, collision or the step cap."""
    turn = -float(robot_observation[1]) / (math.pi / 6) + rng.normal(0.0, 0.3)
    return np.array([rng.uniform(-0.2, 1.0), min(max(turn, -1.0), 1.0)])


def _play_env(config: dict, seeds: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Every step of seeded episodes of one environment, stacked: world state, observation, reward, ends."""
    env = socnav.make_env(config)
    world = env.unwrapped.world
    rows: dict[str, list] = {key: [] for key in ("positions", "velocities", "heading", "robot", "humans",
                                                 "humans_mask", "reward", "terminated", "truncated", "episode")}

    def record(observation, reward, terminated, truncated, episode):
        rows["positions"].append(world.positions[0].copy())
        rows["velocities"].append(world.velocities[0].copy())
        rows["heading"].append(world.heading[0])
        for key in ("robot", "humans", "humans_mask"):
            rows[key].append(observation[key])
        rows["reward"].append(reward)
        rows["terminated"].append(terminated)
        rows["truncated"].append(truncated)
        rows["episode"].append(episode)

    for episode, seed in enumerate(seeds):
        rng = np.random.default_rng(1000 + seed)
        observation, _ = env.reset(seed=seed)
        record(observation, 0.0, False, False, episode)
        for _ in range(MAX_STEPS):
            observation, reward, terminated, truncated, _ = env.step(_action(rng, observation["robot"]))
            record(observation, reward, terminated, truncated, episode)
            if terminated or truncated:
                break
    return {key: np.asarray(value) for key, value in rows.items()}


def _play_batch(config: dict, n_envs: int, seed: int) -> dict[str, np.ndarray]:
    """A batched world stepped directly, finished environments reset on the spot (as the VecEnv does)."""
    world = CrowdWorld(load_config(config), n_envs)
    for env in range(n_envs):
        world.seed(env, seed + env)
    world.reset()
    rng = np.random.default_rng(seed)
    rows: dict[str, list] = {key: [] for key in ("positions", "velocities", "reward", "outcome", "robot", "humans")}
    for _ in range(MAX_STEPS):
        observation = world.observe()
        actions = np.stack([_action(rng, observation["robot"][env]) for env in range(n_envs)])
        result = world.step(actions)
        rows["positions"].append(world.positions.copy())
        rows["velocities"].append(world.velocities.copy())
        rows["reward"].append(result.reward)
        rows["outcome"].append(result.outcome)
        observation = world.observe()
        rows["robot"].append(observation["robot"])
        rows["humans"].append(observation["humans"])
        done = np.flatnonzero(result.outcome)
        if done.size:
            world.reset(done)
    return {key: np.asarray(value) for key, value in rows.items()}


def play_all() -> dict[str, np.ndarray]:
    """Every recorded case, flattened to 'case/array' keys."""
    arrays = {}
    for name, (config, seeds) in ENV_CASES.items():
        arrays.update({f"{name}/{key}": value for key, value in _play_env(config, seeds).items()})
    arrays.update({f"batch/{key}": value for key, value in _play_batch(*BATCH_CASE).items()})
    return arrays


def test_default_config_replays_the_recording_bit_for_bit():
    recorded = np.load(GOLDEN)
    replayed = play_all()
    assert sorted(recorded.files) == sorted(replayed)
    for key in recorded.files:
        assert recorded[key].shape == replayed[key].shape, key
        assert np.array_equal(recorded[key], replayed[key]), f"{key} differs from the recording"


def test_the_recording_covers_the_episode_ends():
    # guards the recording itself: the cases must reach goals, collisions and redraws, not just wander
    recorded = np.load(GOLDEN)
    outcomes = set(recorded["batch/outcome"].ravel().tolist())
    ended = sum(bool(recorded[f"{name}/terminated"].any()) for name in ENV_CASES)
    assert ended >= 2 and len(outcomes) >= 2, (ended, outcomes)


# ---------------------------------------------------------------------------------------------------- registry


def test_the_registry_holds_both_models_and_builds_them_from_the_config():
    assert human_model_names()[:2] == ["orca", "social_force"]
    for name, kind in (("orca", OrcaHumans), ("social_force", SocialForceHumans)):
        model = make_human_model(load_config({"humans": {"model": name}}))
        assert type(model) is kind and model.name == name
        assert isinstance(model, HumanModel), "satisfies the protocol"
    assert load_config().humans.model == "orca", "ORCA is the default"


@pytest.mark.parametrize(("model", "expected"), [
    ("socail_force", "did you mean social_force?"),
    ("ORCA", "did you mean orca?"),
    ("helbing", "allowed: orca, social_force"),
])
def test_an_unknown_model_names_the_field_the_allowed_values_and_a_suggestion(model, expected):
    with pytest.raises(ConfigError) as error:
        load_config({"humans": {"model": model}})
    message = str(error.value)
    assert f"humans.model: unknown human model {model!r}; allowed: orca, social_force" in message
    assert expected in message


@pytest.mark.parametrize(("humans", "field", "expected"), [
    ({"modle": "orca"}, "humans.modle", "did you mean model?"),
    ({"social_force": {"relaxation_tim": 1.0}}, "humans.social_force.relaxation_tim", "did you mean relaxation_time?"),
    ({"social_force": {"relaxation_time": 0.0}}, "humans.social_force.relaxation_time", "greater than 0"),
    ({"social_force": {"fov_factor": 2.0}}, "humans.social_force.fov_factor", "less than or equal to 1"),
    ({"social_force": {"gamma": float("nan")}}, "humans.social_force.gamma", "finite"),
])
def test_the_humans_section_is_validated(humans, field, expected):
    with pytest.raises(ConfigError) as error:
        load_config({"humans": humans})
    assert f"{field}: " in str(error.value) and expected in str(error.value)


def test_a_registered_model_is_selectable_by_name(monkeypatch):
    class Standing:
        """Every human stands still: the smallest model that satisfies the protocol."""

        name, interaction_range, arrival_distance = "standing", 10.0, 0.0

        def velocities(self, crowd: Crowd, compute: np.ndarray) -> np.ndarray:
            return np.where(compute[..., None], 0.0, crowd.velocities)

    monkeypatch.setattr(humans_registry, "HUMAN_MODELS", dict(humans_registry.HUMAN_MODELS))
    register_human_model("standing", lambda config: Standing())
    world = CrowdWorld(load_config({"scenario": "circle_crossing", "humans": {"model": "standing"}}), 1)
    world.seed(0, 0)
    world.reset()
    start = world.positions[0, 1:].copy()
    for _ in range(5):
        world.step(np.array([[0.0, 0.0]]))
    assert np.array_equal(world.positions[0, 1:], start)
    assert "standing humans" in describe_world(world.config)


# ---------------------------------------------------------------------------------------------------- both models


@pytest.mark.parametrize("model", ["orca", "social_force"])
def test_gymnasium_checker_passes_and_episodes_end(model):
    env = socnav.make_env({"scenario": "circle_crossing", "humans": {"model": model}})
    check_env(env, skip_render_check=True)
    outcomes = []
    for seed in range(4):
        observation, _ = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        for _ in range(10_000):
            observation, reward, terminated, truncated, info = env.step(_action(rng, observation["robot"]))
            assert np.isfinite(reward) and all(np.isfinite(value).all() for value in observation.values())
            if terminated or truncated:
                outcomes.append(info["outcome"])
                break
        else:
            pytest.fail("the episode never ended")
    assert len(outcomes) == 4 and "goal" in outcomes, outcomes


def _staged(model: str, attentive: bool, **config):
    """A robot standing in the way of a human walking to its goal 8 m ahead, along -x (360 degree view)."""
    cfg = load_config({"scenario": "circle_crossing", "n_humans": 1, "human_fov_deg": 360,
                       "humans": {"model": model}, **config})
    world = CrowdWorld(cfg, 1)
    state = InitialState.empty(1, world.n_slots)
    state.positions[0, :2], state.goals[0, :2] = [(0.0, 0.0), (4.0, 0.1)], [(0.0, 9.0), (-4.0, 0.1)]
    state.radii[0, :2], state.preferred_speeds[0, :2], state.active[0, :2] = 0.3, 1.0, True
    state.personal_space_radii[0, 1], state.cooperation[0, 1] = 0.5, 0.5
    world.load(0, state)
    world.set_attention(0, np.array([True, attentive]))
    return world


@pytest.mark.parametrize("model", ["orca", "social_force"])
def test_an_inattentive_human_walks_as_if_the_robot_were_absent(model):
    paths = {}
    for label, kwargs in (("attentive", {"attentive": True}), ("inattentive", {"attentive": False}),
                          ("invisible robot", {"attentive": True, "robot_visible": False})):
        world = _staged(model, **kwargs)
        path = []
        for _ in range(24):
            world.step(np.array([[-1.0, 0.0]]))  # the robot stands still
            path.append(world.positions[0, 1].copy())
        paths[label] = np.array(path)
    assert np.array_equal(paths["inattentive"], paths["invisible robot"])
    assert np.abs(paths["attentive"] - paths["inattentive"]).max() > 0.1, "an attentive human avoids the robot"


def test_social_force_disturbance_is_scored_against_the_robot_free_step():
    world = _staged("social_force", attentive=True, reward={"time": 0.0, "progress": 0.0, "personal_space": 0.0,
                                                            "disturbance": 1.0, "social_radius": 10.0})
    for _ in range(8):
        world.step(np.array([[-1.0, 0.0]]))
    expected = world.human_velocities()[0, 1] - world.human_velocities(without_robot=True)[0, 1]
    result = world.step(np.array([[-1.0, 0.0]]))
    assert np.linalg.norm(expected) > 1e-3
    assert result.reward[0] == pytest.approx(-np.linalg.norm(expected) / 1.0, rel=1e-12)


def test_social_force_humans_arrive_and_get_new_goals_in_the_random_scenario():
    # They stop `stop_distance` (0.5 m) from their goal, beyond goal_tolerance (0.3 m): goals are redrawn there.
    world = CrowdWorld(load_config({"scenario": "random", "humans": {"model": "social_force"}}), 1)
    world.seed(0, 3)
    world.reset()
    first_goals = world.goals[0, 1:].copy()
    for _ in range(200):
        result = world.step(np.array([[-1.0, 0.0]]))
        if result.outcome[0]:
            break
    assert world.arrival_distance == 0.5
    assert (np.linalg.norm(world.goals[0, 1:] - first_goals, axis=1) > 0).any(), "some goal was redrawn"


def test_social_force_humans_walk_to_their_goals_at_1_3_v_pref():
    world = _staged("social_force", attentive=False)
    for _ in range(20):  # from rest: v relaxes to v_max with tau = 0.5 s, halving the rest every 0.25 s step
        world.step(np.array([[-1.0, 0.0]]))
    assert world.velocities[0, 1] == pytest.approx([-1.3, 0.0], abs=1.3 * 0.5**19)
    for _ in range(40):
        world.step(np.array([[-1.0, 0.0]]))
    assert np.array_equal(world.velocities[0, 1], [0.0, 0.0]), "stopped near the goal"
    assert 0.0 < np.linalg.norm(world.goals[0, 1] - world.positions[0, 1]) < 0.5


if __name__ == "__main__":
    if sys.argv[1:] != ["--record"]:
        sys.exit("usage: python tests/sim/test_human_models.py --record  (rewrites the golden recording)")
    GOLDEN.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(GOLDEN, **play_all())
    print(f"wrote {GOLDEN} ({GOLDEN.stat().st_size:,} bytes)")
