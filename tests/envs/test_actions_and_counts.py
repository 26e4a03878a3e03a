"""Bad actions and impossible environment counts are clear errors naming the environment, the shape or the
memory the count would need."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from typer.testing import CliRunner

import socnav
from socnav.cli import app
from socnav.config import ConfigError, load_config
from socnav.envs.rollout import rollout_episodes

CONFIG = {"scenario": "circle_crossing", "n_humans": 3}


def test_nan_action_is_refused_naming_the_environment_and_changes_nothing():
    env = socnav.make_env(CONFIG)
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match=r"environment 0 is NaN"):
        env.step([np.nan, 0.0])
    assert env.world.time[0] == 0.0 and np.array_equal(env._observation()["robot"], obs["robot"])
    _, reward, *_ = env.step([0.0, 0.0])
    assert np.isfinite(reward)


def test_nan_row_of_the_vec_env_is_refused_naming_its_index():
    vec = socnav.make_vec_env(CONFIG, n_envs=4)
    vec.seed(0)
    vec.reset()
    actions = np.zeros((4, 2), np.float32)
    actions[2, 1] = np.nan
    actions[3, 0] = np.nan
    with pytest.raises(ValueError, match=r"environment 2 \(and 1 other\(s\)\) is NaN"):
        vec.step(actions)
    _, rewards, _, _ = vec.step(np.zeros((4, 2), np.float32))
    assert np.isfinite(rewards).all()


def test_infinite_actions_are_clipped_like_any_out_of_range_action():
    """Documented: +-inf is clipped to the action bounds (as SB3 clips a Box policy's actions), NaN is refused."""
    stepped = []
    for action in ([np.inf, -np.inf], [1.0, -1.0], [7.0, -3.0]):
        env = socnav.make_env(CONFIG)
        env.reset(seed=3)
        obs, reward, *_ = env.step(action)
        stepped.append((obs["robot"], reward))
    for robot, reward in stepped[::2]:
        assert np.array_equal(robot, stepped[1][0]) and reward == stepped[1][1] and np.isfinite(reward)


def test_rollout_refuses_a_policy_that_outputs_nan():
    class NanPolicy:
        def predict(self, observation, state=None, episode_start=None, deterministic=True):
            actions = np.zeros((len(observation["robot"]), 2))
            actions[1] = np.nan
            return actions, None

    with pytest.raises(ValueError, match="environment 1"):
        rollout_episodes(NanPolicy(), CONFIG, n_episodes=4, n_envs=4)


def test_an_env_count_that_cannot_fit_is_refused_with_the_estimate_before_allocating():
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError, match=r"n_envs=10,000,000 environments need about [\d.,]+ GiB.*use at most"):
            socnav.make_vec_env(CONFIG, n_envs=10_000_000)
        assert tracemalloc.get_traced_memory()[1] < 20 * 2**20
    finally:
        tracemalloc.stop()
    from socnav.envs.env import check_env_count

    for bad in (0, -3, True, 2.0):
        with pytest.raises(ConfigError, match="n_envs must be a positive integer"):
            check_env_count(bad, load_config(CONFIG))


@pytest.mark.parametrize("config", [CONFIG, {"scenario": "random", "n_humans": 20, "max_humans": 20}])
def test_the_memory_estimate_matches_what_environments_take(config):
    """The estimate is within [1x, 2x] of the memory a VecEnv actually allocates while stepping."""
    from socnav.envs.env import env_memory_estimate

    n_envs = 400
    warm = socnav.make_vec_env(config, n_envs=2)  # numba compiles on the first step: not the environments' memory
    warm.reset()
    warm.step(np.zeros((2, 2), np.float32))
    tracemalloc.start()
    try:
        vec = socnav.make_vec_env(config, n_envs=n_envs)
        vec.seed(0)
        vec.reset()
        for _ in range(3):
            vec.step(np.zeros((n_envs, 2), np.float32))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    estimate = env_memory_estimate(load_config(config), n_envs)
    assert peak <= estimate <= 2 * peak, (peak, estimate)


def test_cli_refuses_impossible_env_counts_before_writing(tmp_path):
    runner = CliRunner()
    out = tmp_path / "run"
    result = runner.invoke(app, ["train", "--scenario", "position_swap", "--n-envs", "10000000", "--timesteps", "100",
                                 "--out", str(out)])
    assert result.exit_code == 2 and "--n-envs=10,000,000" in result.output and "GiB" in result.output
    assert not out.exists()
    result = runner.invoke(app, ["evaluate", "--controller", "orca", "--n-envs", "10000000", "--episodes", "10000000",
                                 "--out", str(tmp_path / "x.csv")])
    assert result.exit_code == 2 and "--n-envs=10,000,000" in result.output


@pytest.mark.parametrize("shape", [(8,), (2, 4), (4, 2, 1), (4, 1), (3, 2)])
def test_vec_env_refuses_actions_of_another_shape_instead_of_reshaping(shape):
    # (8,) and (2, 4) hold the right number of values: reshaped, they would give environment 1 another's action.
    vec = socnav.make_vec_env(CONFIG, n_envs=4)
    vec.seed(0)
    vec.reset()
    with pytest.raises(ValueError, match=r"shape \(4, 2\)") as error:
        vec.step(np.zeros(shape, np.float32))
    assert str(shape) in str(error.value)
    _, rewards, _, _ = vec.step(np.zeros((4, 2), np.float32))  # the environment is still usable
    assert np.isfinite(rewards).all()
