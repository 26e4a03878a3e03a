"""The environments against Gymnasium's and SB3's checkers, seeding, batching and SB3's VecEnv conventions."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.vec_env import DummyVecEnv

import socnav
from socnav.sim.scenarios import scenario_names


@pytest.mark.parametrize("scenario", scenario_names(self_contained=True))  # replay: test_replay_and_mix.py
def test_gymnasium_checker_passes(scenario):
    env = socnav.make_env({"scenario": scenario}, render_mode="rgb_array")
    gym_check_env(env, skip_render_check=False)


@pytest.mark.parametrize("scenario", ["circle_crossing", "random"])
def test_sb3_checker_passes(scenario):
    sb3_check_env(socnav.make_env({"scenario": scenario}), warn=True)


def test_registered_gymnasium_ids_build_the_right_scenario():
    env = gym.make("socnav/CircleInteraction-v0", n_humans=2)
    assert env.unwrapped.config.scenario == "circle_interaction"
    obs, _ = env.reset(seed=3)
    assert obs["humans_mask"].sum() == 2


def _random_actions(n_steps, n_envs, seed=123):
    return np.random.default_rng(seed).uniform(-1, 1, size=(n_steps, n_envs, 2)).astype(np.float32)


@pytest.mark.parametrize("scenario", ["circle_crossing", "random"])
def test_vec_env_matches_single_envs_across_resets(scenario):
    """Env i of a VecEnv seeded s is step for step the single env reset with seed s+i, auto-resets included."""
    n_envs, n_steps, seed = 3, 260, 11
    config = {"scenario": scenario, "perturbation": {"observation_noise": 0.1, "heading_noise": 0.2}}
    actions = _random_actions(n_steps, n_envs)
    vec = socnav.make_vec_env(config, n_envs=n_envs)
    vec.seed(seed)
    vec_obs = [vec.reset()]
    vec_rewards, vec_dones = [], []
    for t in range(n_steps):
        obs, rewards, dones, _ = vec.step(actions[t])
        vec_obs.append(obs)
        vec_rewards.append(rewards)
        vec_dones.append(dones)
    assert np.any(vec_dones), "the test should cross at least one episode boundary"
    for i in range(n_envs):
        env = socnav.make_env(config)
        obs, _ = env.reset(seed=seed + i)
        np.testing.assert_array_equal(obs["humans"], vec_obs[0]["humans"][i])
        for t in range(n_steps):
            obs, reward, terminated, truncated, _ = env.step(actions[t, i])
            assert np.float32(reward) == vec_rewards[t][i]
            assert (terminated or truncated) == vec_dones[t][i]
            if terminated or truncated:
                obs, _ = env.reset()
            for key in obs:
                np.testing.assert_array_equal(obs[key], vec_obs[t + 1][key][i], err_msg=f"{key} env {i} step {t}")


def test_terminal_observation_and_truncation_flags():
    vec = socnav.make_vec_env({"scenario": "position_swap", "timeout_margin": 0.0, "timeout_factor": 0.05}, n_envs=2)
    vec.seed(0)
    vec.reset()
    stand_still = np.tile([[-1.0, 0.0]], (2, 1))
    for _ in range(50):
        _, _, dones, infos = vec.step(stand_still)
        if dones.any():
            break
    info = infos[int(np.flatnonzero(dones)[0])]
    assert info["TimeLimit.truncated"] is True
    assert info["episode"]["outcome"] == "timeout"
    assert set(info["terminal_observation"]) == {"robot", "humans", "humans_mask"}


def test_same_seed_same_episode_and_different_seed_differs():
    def play(seed):
        env = socnav.make_env({"scenario": "circle_crossing"})
        obs, _ = env.reset(seed=seed)
        trace = [obs["humans"].copy()]
        for action in _random_actions(30, 1)[:, 0]:
            obs, *_ = env.step(action)
            trace.append(obs["humans"].copy())
        return np.stack(trace)

    np.testing.assert_array_equal(play(5), play(5))
    assert not np.array_equal(play(5), play(6))


def test_sb3_dummy_vec_env_of_single_envs_matches_batched_env():
    """Our batched VecEnv and SB3's own DummyVecEnv over SocialNavEnv agree, so SB3 tooling sees the same world."""
    config = {"scenario": "circle_interaction"}
    dummy = DummyVecEnv([lambda: socnav.make_env(config) for _ in range(2)])
    ours = socnav.make_vec_env(config, n_envs=2)
    dummy.seed(4)
    ours.seed(4)
    a, b = dummy.reset(), ours.reset()
    for step_actions in _random_actions(120, 2, seed=9):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
        a, ra, da, _ = dummy.step(step_actions)
        b, rb, db, _ = ours.step(step_actions)
        np.testing.assert_allclose(ra, rb, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(da, db)


def test_rgb_array_render_and_vec_images():
    env = socnav.make_env({"scenario": "circle_crossing"}, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    vec = socnav.make_vec_env({"scenario": "circle_crossing"}, n_envs=2, render_mode="rgb_array")
    vec.reset()
    assert len(vec.get_images()) == 2


def test_info_reports_metrics_at_episode_end():
    env = socnav.make_env({"scenario": "position_swap"})
    env.reset(seed=1)
    for _ in range(500):
        _, _, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))
        assert {"nearest_gap", "nearest_relative_speed", "intrusions", "time"} <= set(info)
        if terminated or truncated:
            break
    episode = info["episode"]
    for key in ("outcome", "return", "length", "path_length", "time_to_goal", "min_gap", "intrusion_steps",
                "intrusion_events", "r", "l"):
        assert key in episode
    assert episode["length"] == info["time"] / env.config.time_step
