"""Tests of the ODV-PPO network: LSTM extractor (trimming, padding), dropout placement and modes, ODV head.
Uses the dummy socnav spaces of conftest.py; no training beyond a few rollout steps.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from torch import nn
from torch.nn.utils.rnn import pack_padded_sequence

from socnav.rl import ALGOS, HumanLSTMExtractor, ODVActorCriticPolicy

DROPOUT_ALGOS = ["ppo-drop", "odv-ppo-drop"]
ODV_ALGOS = ["odv-ppo-noloss", "odv-ppo", "odv-ppo-drop"]


def packed_reference(extractor: HumanLSTMExtractor, humans: th.Tensor, n: th.Tensor) -> th.Tensor:
    """Final top-layer hidden state computed the textbook way, with pack_padded_sequence (dropout off)."""
    h = th.zeros(humans.shape[0], extractor.lstm_hidden_size)
    real = n > 0
    if not real.any():
        return h
    packed = pack_padded_sequence(humans[real], n[real], batch_first=True, enforce_sorted=False)
    for lstm in extractor.lstm_layers:
        packed, (h_n, _) = lstm(packed)
    h[real] = h_n[-1]
    return h


def make_extractor(dropout_p: float = 0.0, seed: int = 0) -> HumanLSTMExtractor:
    """An extractor for the socnav spaces (10 humans), in eval mode."""
    th.manual_seed(seed)
    space = spaces.Dict(
        {
            "robot": spaces.Box(-np.inf, np.inf, (5,), np.float32),
            "humans": spaces.Box(-np.inf, np.inf, (10, 7), np.float32),
            "humans_mask": spaces.Box(0.0, 1.0, (10,), np.float32),
        }
    )
    return HumanLSTMExtractor(space, lstm_hidden_size=64, n_lstm_layers=2, dropout_p=dropout_p).eval()


# ---- LSTM extractor ----------------------------------------------------------------------------------------
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(counts=st.lists(st.integers(0, 10), min_size=1, max_size=12), seed=st.integers(0, 2**16))
def test_trimmed_lstm_equals_pack_padded_sequence(obs_batch, counts: list[int], seed: int) -> None:
    ext = make_extractor()
    obs = obs_batch(len(counts), seed=seed, n=counts)
    n = th.tensor(counts)
    with th.no_grad():
        h = ext.encode_humans(obs["humans"], obs["humans_mask"])
        ref = packed_reference(ext, obs["humans"], n)
    th.testing.assert_close(h, ref, atol=1e-6, rtol=1e-5)
    assert th.all(h[n == 0] == 0)


def test_padded_rows_have_no_influence(obs_batch) -> None:
    ext = make_extractor()
    obs = obs_batch(32, seed=1)
    garbage = {k: v.clone() for k, v in obs.items()}
    pad = garbage["humans_mask"] == 0
    garbage["humans"][pad] = th.randn(int(pad.sum()), 7) * 1e3  # huge values in every padded row
    with th.no_grad():
        th.testing.assert_close(ext(obs), ext(garbage), atol=0, rtol=0)


def test_no_humans_gives_zero_hidden_state(obs_batch) -> None:
    ext = make_extractor()
    obs = obs_batch(5, n=[0] * 5)
    features, h = ext.forward_with_h(obs)
    assert th.all(h == 0)
    th.testing.assert_close(features[:, 64:], obs["robot"])  # [h, robot]
    assert ext.features_dim == 69


# ---- dropout placement and modes -----------------------------------------------------------------------------
@pytest.mark.parametrize("algo", DROPOUT_ALGOS)
def test_dropout_in_extractor_and_actor_not_in_critic(small_model, algo: str) -> None:
    policy: ODVActorCriticPolicy = small_model(algo).policy
    ext_drop = [m for m in policy.features_extractor.modules() if isinstance(m, nn.Dropout)]
    actor_drop = [m for m in policy.mlp_extractor.policy_net.modules() if isinstance(m, nn.Dropout)]
    critic_drop = [m for m in policy.mlp_extractor.value_net.modules() if isinstance(m, nn.Dropout)]
    assert len(ext_drop) == 3  # LSTM input, between the 2 layers, on h
    assert len(actor_drop) == 2  # after each hidden layer
    assert critic_drop == []
    assert not isinstance(policy.value_net, nn.Dropout)
    assert all(m.p == pytest.approx(0.1) for m in ext_drop + actor_drop)
    assert policy.dropout_layers() == ext_drop + actor_drop
    assert policy.p_test == pytest.approx(0.5)


@pytest.mark.parametrize("algo", DROPOUT_ALGOS)
def test_dropout_active_in_training_off_in_prediction(small_model, obs_batch, algo: str) -> None:
    policy = small_model(algo).policy
    obs = obs_batch(16, seed=2)
    policy.set_training_mode(True)
    h1, mu1, _ = policy.action_stats(obs)
    h2, mu2, _ = policy.action_stats(obs)
    assert not th.equal(mu1, mu2)
    assert not th.equal(h1, h2)
    np_obs = {k: v.numpy() for k, v in obs.items()}
    a1, _ = policy.predict(np_obs, deterministic=True)
    a2, _ = policy.predict(np_obs, deterministic=True)
    np.testing.assert_array_equal(a1, a2)
    assert not policy.training  # predict() switched to eval mode
    _, mu_eval, _ = policy.action_stats(obs)
    np.testing.assert_allclose(a1, np.clip(mu_eval.numpy(), -1, 1), rtol=1e-6, atol=1e-6)


def test_no_dropout_presets_are_deterministic_in_training_mode(small_model, obs_batch) -> None:
    policy = small_model("odv-ppo").policy
    obs = obs_batch(8, seed=3)
    policy.set_training_mode(True)
    assert th.equal(policy.action_stats(obs)[1], policy.action_stats(obs)[1])


def test_mc_dropout_context_enables_only_dropout_and_restores(small_model, obs_batch) -> None:
    policy = small_model("odv-ppo-drop").policy
    policy.set_training_mode(False)
    obs = obs_batch(8, seed=4)
    _, mu_eval, _ = policy.action_stats(obs)
    with policy.mc_dropout(0.5):
        for module in policy.modules():
            assert module.training == isinstance(module, nn.Dropout)
        assert all(d.p == 0.5 for d in policy.dropout_layers())
        samples = th.stack([policy.action_stats(obs)[1] for _ in range(3)])
    assert not th.equal(samples[0], samples[1])
    assert not any(m.training for m in policy.modules())
    assert all(d.p == pytest.approx(0.1) for d in policy.dropout_layers())
    th.testing.assert_close(policy.action_stats(obs)[1], mu_eval, atol=0, rtol=0)
    # training mode is restored too, and p defaults to the stored p_test
    policy.set_training_mode(True)
    with policy.mc_dropout():
        assert all(d.p == 0.5 for d in policy.dropout_layers())
        assert not policy.mlp_extractor.policy_net[0].training
    assert all(m.training for m in policy.modules())
    with pytest.raises(ValueError), policy.mc_dropout(1.0):
            pass


# ---- ODV head ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("algo", ALGOS)
def test_sigma_is_observation_dependent_only_for_odv(small_model, obs_batch, algo: str) -> None:
    policy = small_model(algo).policy
    policy.set_training_mode(False)
    h, mean, log_std = policy.action_stats(obs_batch(2, seed=5, n=[3, 7]))
    assert h.shape == (2, 64) and mean.shape == (2, 2) and log_std.shape == (2, 2)
    if algo in ODV_ALGOS:
        assert policy.odv and hasattr(policy, "log_std_net") and not hasattr(policy, "log_std")
        assert not th.equal(log_std[0], log_std[1])
    else:
        assert not policy.odv and isinstance(policy.log_std, nn.Parameter)
        assert th.equal(log_std[0], log_std[1])
        th.testing.assert_close(log_std[0], policy.log_std.detach())


@pytest.mark.parametrize("scale", [1e6, -1e6])
def test_log_std_clamp_holds_for_extreme_inputs(small_model, obs_batch, scale: float) -> None:
    policy = small_model("odv-ppo-drop").policy
    with th.no_grad():
        policy.log_std_net.weight.fill_(scale)
        policy.log_std_net.bias.fill_(scale)
    obs = {k: v * 1e6 if k != "humans_mask" else v for k, v in obs_batch(16, seed=6).items()}
    for training in (False, True):
        policy.set_training_mode(training)
        _, mean, log_std = policy.action_stats(obs)
        assert th.isfinite(mean).all() and th.isfinite(log_std).all()
        assert log_std.min() >= -20.0 and log_std.max() <= 0.25
        assert th.all((log_std == 0.25) | (log_std == -20.0))  # saturated at one of the bounds
    # a sampled action is still a finite Gaussian sample, clipped to the box by predict()
    actions, _ = policy.predict({k: v.numpy() for k, v in obs.items()})
    assert np.isfinite(actions).all() and np.abs(actions).max() <= 1.0


# ---- feature range tracking ----------------------------------------------------------------------------------
def test_feature_range_tracks_rollout_forward_only(small_model, obs_batch) -> None:
    policy = small_model("odv-ppo-drop").policy
    policy.set_training_mode(False)
    h_min, h_max = policy.feature_range
    assert th.all(th.isinf(h_min)) and th.all(th.isinf(h_max))
    obs = obs_batch(32, seed=7)
    with th.no_grad():
        policy(obs)  # outside the context: no update
    assert th.all(th.isinf(policy.feature_range[0]))
    with policy.feature_range_tracking(), th.no_grad():
        policy(obs)
        policy(obs_batch(32, seed=8))
    h = th.cat([policy.action_stats(obs)[0], policy.action_stats(obs_batch(32, seed=8))[0]])
    th.testing.assert_close(policy.feature_range[0], h.min(0).values)
    th.testing.assert_close(policy.feature_range[1], h.max(0).values)
    assert "features_extractor.h_min" in policy.state_dict()


def test_feature_range_updated_by_learn(small_model) -> None:
    model = small_model("odv-ppo-drop")
    model.learn(128)
    h_min, h_max = model.policy.feature_range
    assert th.isfinite(h_min).all() and th.isfinite(h_max).all()
    assert th.all(h_min <= h_max) and th.any(h_min < h_max)
