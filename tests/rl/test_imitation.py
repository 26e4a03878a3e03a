"""Behaviour cloning (`socnav.rl.imitation`): the teacher's episodes are kept whole with their returns (checked
against the episode returns the environment reports), and a cloned policy acts like its teacher."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.vec_env import VecEnvWrapper

import socnav
from socnav.controllers import make_controller
from socnav.envs.vec_env import SocialNavVecEnv
from socnav.rl import make_model
from socnav.rl.imitation import Demonstrations, clone, collect_demonstrations

WORLD = {"scenario": "circle_crossing", "n_humans": 2}
TINY = {"lstm_hidden_size": 16, "net_arch_pi": (32,), "net_arch_vf": (32,)}


class EpisodeLog(VecEnvWrapper):
    """Records the ``episode`` entry (return ``r``, length ``l``) of every episode that ends."""

    def __init__(self, venv):
        super().__init__(venv)
        self.episodes: list[dict] = []

    def reset(self):
        return self.venv.reset()

    def step_wait(self):
        observation, reward, done, infos = self.venv.step_wait()
        self.episodes.extend(infos[index]["episode"] for index in np.flatnonzero(done))
        return observation, reward, done, infos


@pytest.fixture(scope="module")
def demonstrations_and_log():
    env = EpisodeLog(SocialNavVecEnv(WORLD, n_envs=4))
    env.venv.seed(0)
    teacher = make_controller("orca", socnav.load_config(WORLD))
    return collect_demonstrations(env, teacher, 600, gamma=1.0), env.episodes


def test_each_finished_episode_is_kept_whole_with_its_return(demonstrations_and_log):
    """With gamma = 1 the return to go of an episode's first step is the episode's return; the steps kept are
    exactly the finished episodes' steps, in one block per episode."""
    demonstrations, episodes = demonstrations_and_log
    assert len(episodes) >= 4
    lengths = [int(episode["l"]) for episode in episodes]
    assert len(demonstrations) == sum(lengths)
    starts = np.cumsum([0, *lengths[:-1]])
    np.testing.assert_allclose(demonstrations.returns[starts], [episode["r"] for episode in episodes], atol=1e-3)
    for start, length in zip(starts, lengths, strict=True):  # one outcome per episode block
        assert len(set(demonstrations.outcomes[start:start + length].tolist())) == 1
    assert set(demonstrations.observations) == {"robot", "humans", "humans_mask"}
    assert np.all(np.abs(demonstrations.actions) <= 1.0)


def test_discounted_returns_to_go_are_computed_backwards():
    env = SocialNavVecEnv(WORLD, n_envs=1)
    env.seed(3)
    log = EpisodeLog(env)
    demonstrations = collect_demonstrations(log, make_controller("straight", env.config), 200, gamma=0.9)
    returns = demonstrations.returns[: int(log.episodes[0]["l"])].astype(np.float64)
    rewards = returns[:-1] - 0.9 * returns[1:]  # r_t = G_t - gamma G_{t+1}
    # the undiscounted sum of the recovered rewards (and the last one, G_T = r_T) is the episode's return
    assert rewards.sum() + returns[-1] == pytest.approx(log.episodes[0]["r"], abs=1e-3)


def test_a_cloned_policy_acts_like_its_teacher(demonstrations_and_log):
    th.set_num_threads(1)
    demonstrations, _ = demonstrations_and_log
    model = make_model("odv-ppo-drop", SocialNavVecEnv(WORLD, n_envs=1), seed=0, overrides=TINY)

    def error() -> float:
        actions, _ = model.policy.predict(demonstrations.observations, deterministic=True)
        return float(np.abs(actions - demonstrations.actions).mean())

    before = error()
    history = clone(model.policy, demonstrations, epochs=30, batch_size=64, seed=0)
    assert history[-1]["action_mse"] < history[0]["action_mse"]
    assert history[-1]["value_loss"] < history[0]["value_loss"]
    assert error() < 0.5 * before


def test_imitating_an_outcome_that_never_happened_is_a_clear_error(demonstrations_and_log):
    demonstrations, _ = demonstrations_and_log
    model = make_model("odv-ppo-drop", SocialNavVecEnv(WORLD, n_envs=1), seed=0, overrides=TINY)
    with pytest.raises(ValueError, match=r"imitate=\['collision_wall'\]: no demonstration ended so"):
        clone(model.policy, demonstrations, epochs=1, imitate={"collision_wall"})
    with pytest.raises(ValueError, match="no demonstrations"):
        empty = Demonstrations({key: value[:0] for key, value in demonstrations.observations.items()},
                               demonstrations.actions[:0], demonstrations.returns[:0], demonstrations.outcomes[:0])
        clone(model.policy, empty, epochs=1)


def test_with_a_driver_the_driver_moves_and_the_teacher_labels():
    """DAgger's collection: the episodes are the driver's (their returns are those the environment reports for
    the driver's episodes) and each kept action is what the teacher does at that state."""
    config = socnav.load_config(WORLD)
    teacher, driver = make_controller("orca", config), make_controller("straight", config)
    driven, alone = EpisodeLog(SocialNavVecEnv(WORLD, n_envs=4)), EpisodeLog(SocialNavVecEnv(WORLD, n_envs=4))
    driven.venv.seed(1)
    alone.venv.seed(1)
    demonstrations = collect_demonstrations(driven, teacher, 400, gamma=1.0, driver=driver)
    collect_demonstrations(alone, driver, 400, gamma=1.0)
    assert [episode["r"] for episode in driven.episodes] == [episode["r"] for episode in alone.episodes]
    relabelled, _ = teacher.predict(demonstrations.observations)
    np.testing.assert_allclose(demonstrations.actions, np.clip(relabelled, -1, 1), atol=1e-6)
    straight, _ = driver.predict(demonstrations.observations)
    assert np.abs(straight - demonstrations.actions).max() > 0.1  # the two controllers do differ here


class AnnouncedStraight:
    """The straight controller, recording which environments it is told begin an episode."""

    def __init__(self, config):
        self.inner = make_controller("straight", config)
        self.started: list[list[int]] = []

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        return self.inner.predict(observation, state, episode_start, deterministic)

    def on_episode_start(self, envs):
        self.started.append(sorted(int(env) for env in envs))


def test_a_driver_is_told_when_episodes_start():
    """A driver that keeps per-environment state (the safety layer's) hears of every new episode, as the teacher
    does: all environments first, then each environment whose episode ended, in the step it ended."""
    config = socnav.load_config(WORLD)
    driver = AnnouncedStraight(config)
    env = EpisodeLog(SocialNavVecEnv(WORLD, n_envs=4))
    env.venv.seed(2)
    collect_demonstrations(env, make_controller("orca", config), 400, gamma=1.0, driver=driver)
    assert driver.started[0] == [0, 1, 2, 3]
    announced = sum(len(envs) for envs in driver.started[1:])
    assert announced == len(env.episodes) > 0


class ObservationLog(VecEnvWrapper):
    """Records every observation the wrapped VecEnv returns (reset's, then each step's)."""

    def __init__(self, venv):
        super().__init__(venv)
        self.observations: list[dict] = []

    def reset(self):
        observation = self.venv.reset()
        self.observations.append(observation)
        return observation

    def step_wait(self):
        observation, reward, done, infos = self.venv.step_wait()
        self.observations.append(observation)
        return observation, reward, done, infos


def test_a_cloned_policys_feature_range_is_that_of_the_states_it_drives_into():
    """`track_feature_range` gives a policy trained without rollouts what ODV-PPO's rollouts give: h_min / h_max
    are the element-wise extremes of the hidden states at exactly the states it reached, recomputed here from the
    recorded observations; before it the range is untracked (u_feat 0)."""
    from socnav.rl.imitation import track_feature_range

    model = make_model("odv-ppo-drop", SocialNavVecEnv(WORLD, n_envs=1), seed=0, overrides=TINY)
    policy = model.policy
    assert not th.isfinite(policy.feature_range[0]).any()
    env = ObservationLog(SocialNavVecEnv(WORLD, n_envs=4))
    env.venv.seed(3)
    track_feature_range(policy, env, 50)  # 13 steps of 4 environments
    reached = env.observations[:13]
    assert len(env.observations) == 14
    with th.no_grad():
        hidden = th.cat([policy._features(policy.obs_to_tensor(obs)[0])[1] for obs in reached])
    h_min, h_max = policy.feature_range
    th.testing.assert_close(h_min, hidden.min(dim=0).values)
    th.testing.assert_close(h_max, hidden.max(dim=0).values)
    assert bool((h_max > h_min).any())
