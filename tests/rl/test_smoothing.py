"""Smooth driving: the training-time turning and action-change costs, by hand and on the real environment (the
wrapped rewards are the world's rewards minus exactly those costs), and wired into `train` by the config."""

from __future__ import annotations

import numpy as np
import pytest

from socnav.envs.vec_env import make_vec_env
from socnav.rl.smoothing import SmoothnessPenalty, smoothness_costs

WORLD = {"scenario": "position_swap", "n_humans": 1}


def test_costs_by_hand():
    actions = np.array([[0.5, -1.0], [1.0, 0.25]])
    previous = np.array([[0.5, 1.0], [0.0, 0.25]])
    # env 0: |heading| 1 -> 0.1 * 1; change (0 + 2) / 2 = 1 -> 0.2 * 1; env 1: no previous action: turning only
    costs = smoothness_costs(actions, previous, np.array([True, False]), turn_penalty=0.1, action_change_penalty=0.2)
    np.testing.assert_allclose(costs, [0.1 + 0.2, 0.1 * 0.25])


def _play(env, actions):
    env.seed(3)
    env.reset()
    rewards, dones = [], []
    for action in actions:
        _, reward, done, _ = env.step(action)
        rewards.append(reward.copy())
        dones.append(done.copy())
    return np.array(rewards), np.array(dones)


def test_wrapped_rewards_are_the_worlds_minus_the_costs():
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.5, 1.5, size=(250, 2, 2))  # beyond the bounds too: the costs read the clipped actions
    plain, dones = _play(make_vec_env(WORLD, n_envs=2), actions)
    wrapped, again = _play(SmoothnessPenalty(make_vec_env(WORLD, n_envs=2), 0.1, 0.2), actions)
    np.testing.assert_array_equal(dones, again)  # the costs change the reward, never the episodes
    assert dones.any()  # an episode ended and restarted inside the 250 steps
    clipped = np.clip(actions, -1.0, 1.0)
    expected = plain.copy()
    for t in range(len(actions)):
        has_previous = np.ones(2, dtype=bool) if t else np.zeros(2, dtype=bool)
        if t:
            has_previous &= ~dones[t - 1]
        expected[t] -= smoothness_costs(clipped[t], clipped[t - 1], has_previous, 0.1, 0.2)
    np.testing.assert_allclose(wrapped, expected, rtol=1e-5, atol=1e-6)


def test_negative_penalty_is_refused():
    with pytest.raises(ValueError, match="turn_penalty"):
        SmoothnessPenalty(make_vec_env(WORLD, n_envs=1), -0.1, 0.0)
    from socnav.rl.presets import resolve_config

    with pytest.raises(ValueError, match="action_change_penalty"):
        resolve_config("odv-ppo-drop", {"action_change_penalty": -1.0})


def test_train_learns_from_the_penalised_reward(tmp_path):
    """A run with the costs records them in its config and trains behind the wrapper (the same seed without them
    learns from other rewards, so other weights)."""
    import torch

    from socnav.rl.persistence import load_policy
    from socnav.rl.training import train

    plain = train(WORLD, "odv-ppo-drop", 0, 256, tmp_path / "plain", n_envs=2, eval_episodes=1, tensorboard=False)
    smooth = train(WORLD, "odv-ppo-drop", 0, 256, tmp_path / "smooth", n_envs=2, eval_episodes=1, tensorboard=False,
                   overrides={"turn_penalty": 1.0, "action_change_penalty": 1.0})
    a, b = load_policy(plain.model_path), load_policy(smooth.model_path)
    assert b.socnav_metadata["algo_config"]["turn_penalty"] == 1.0
    assert a.socnav_metadata["algo_config"]["turn_penalty"] == 0.0
    differs = [not torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values(),
                                                       strict=True)]
    assert any(differs)
