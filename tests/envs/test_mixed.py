"""`MixedVecEnv`: several worlds side by side are, environment for environment, the worlds stepped alone (same seeds,
same actions, same observations, rewards and ends); worlds that observe different layouts are refused; a policy
trains on a mixture."""

from __future__ import annotations

import numpy as np
import pytest

from socnav.envs.mixed import MixedVecEnv
from socnav.envs.vec_env import SocialNavVecEnv

CORRIDOR = {"scenario": "corridor", "n_humans": 3, "scan": {"beams": 18}}
DOORWAY = {"scenario": "doorway", "n_humans": 2, "scan": {"beams": 18}}


def test_a_mixture_steps_each_world_as_alone():
    mixed = MixedVecEnv([CORRIDOR, DOORWAY], [2, 3])
    alone = [SocialNavVecEnv(CORRIDOR, n_envs=2), SocialNavVecEnv(DOORWAY, n_envs=3)]
    mixed.seed(7)
    alone[0].seed(7)
    alone[1].seed(9)  # the mixture's environment 2 is the doorway's environment 0: seed 7 + 2
    observation = mixed.reset()
    parts = [env.reset() for env in alone]
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(60):
        for key, value in observation.items():
            np.testing.assert_array_equal(value, np.concatenate([part[key] for part in parts]), err_msg=key)
        actions = rng.uniform(-1, 1, size=(5, 2)).astype(np.float32)
        observation, rewards, dones, infos = mixed.step(actions)
        results = [alone[0].step(actions[:2]), alone[1].step(actions[2:])]
        parts = [result[0] for result in results]
        np.testing.assert_array_equal(rewards, np.concatenate([result[1] for result in results]))
        np.testing.assert_array_equal(dones, np.concatenate([result[2] for result in results]))
        assert [info.get("outcome") for info in infos] == [info.get("outcome") for result in results
                                                            for info in result[3]]
        ends += int(dones.sum())
    assert ends > 0  # episodes ended and restarted in both
    assert mixed.get_attr("config", [0, 4])[1].scenario == "doorway"
    assert mixed.num_envs == 5


def test_worlds_with_other_layouts_are_refused():
    with pytest.raises(ValueError, match=r"configs\[1\] \(circle_crossing\) observes another layout .*'pose'"):
        MixedVecEnv([CORRIDOR, {"scenario": "circle_crossing", "scan": {"beams": 18}}])
    with pytest.raises(ValueError, match=r"n_envs: one count per world \(2\), got 3"):
        MixedVecEnv([CORRIDOR, DOORWAY], [1, 2, 3])
    with pytest.raises(ValueError, match="at least one world"):
        MixedVecEnv([])


def test_a_policy_trains_on_a_mixture():
    import torch

    from socnav.rl import make_model

    torch.set_num_threads(1)
    env = MixedVecEnv([CORRIDOR, DOORWAY], 2)
    model = make_model("odv-ppo-drop", env, seed=0, overrides={"lstm_hidden_size": 8, "net_arch_pi": (16,),
                                                               "net_arch_vf": (16,), "n_steps": 32, "batch_size": 64})
    model.learn(256)
    assert model.num_timesteps >= 256
