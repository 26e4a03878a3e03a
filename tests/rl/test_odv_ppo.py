"""Tests of the ODVPPO algorithm and the presets: variance loss, NaN guard, save/load, short learn() runs.
Runs on the dummy socnav env of conftest.py with tiny rollouts (4 envs x 32 steps).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch as th
from pydantic import ValidationError

from socnav.rl import (
    ALGOS,
    ODVPPO,
    PRESETS,
    NonFiniteError,
    large_batch_overrides,
    make_model,
    resolve_config,
    variance_loss,
)

ODV_ALGOS = ["odv-ppo-noloss", "odv-ppo", "odv-ppo-drop"]

# Fixed batch with known sigma: rows (sigma_speed, sigma_heading).
SIGMA = th.tensor([[0.5, 2.0], [1.0, 1.5]])
# sigma^2 = [[0.25, 4.0], [1.0, 2.25]]; 1/2 ||sigma^2||^2 = [8.03125, 3.03125]; batch mean = 5.53125
HAND_MEAN_TARGET0 = 0.5 * (0.25**2 + 4.0**2 + 1.0**2 + 2.25**2) / 2


# ---- variance loss -----------------------------------------------------------------------------------------------
def test_variance_loss_matches_hand_computation() -> None:
    log_std = SIGMA.log().requires_grad_(True)
    assert pytest.approx(5.53125) == HAND_MEAN_TARGET0
    assert variance_loss(log_std).item() == pytest.approx(5.53125)
    # (t / T) * lambda_sigma = (1024 / 4096) * 0.3 = 0.075
    assert variance_loss(log_std, 0.0, coef=0.075).item() == pytest.approx(0.075 * 5.53125)
    # per-dimension target: 1/2 [(0.25-0.25)^2 + (4-1)^2] = 4.5 ; 1/2 [(1-0.25)^2 + (2.25-1)^2] = 1.0625
    assert variance_loss(log_std, [0.25, 1.0]).item() == pytest.approx((4.5 + 1.0625) / 2)
    # gradient: d/d log_sigma of 1/2 (sigma^2)^2 / B = 2 sigma^4 / B
    variance_loss(log_std).backward()
    th.testing.assert_close(log_std.grad, 2 * SIGMA**4 / 2)


def test_train_adds_scheduled_variance_loss(small_model, recorder, monkeypatch) -> None:
    """The logged train/variance_loss is (t/T) * lambda * hand value for a policy forced to the known sigma."""
    model: ODVPPO = small_model("odv-ppo")
    model.learn(128)  # sets up logger and fills the rollout buffer
    writer = recorder(model)
    original = model.policy.evaluate_actions_and_log_std

    def known_sigma(obs, actions):
        values, log_prob, entropy, log_std = original(obs, actions)
        fixed = SIGMA[th.arange(len(log_std)) % 2].log()  # alternate the two known rows
        return values, log_prob, entropy, fixed + 0.0 * log_std  # keep the graph

    monkeypatch.setattr(model.policy, "evaluate_actions_and_log_std", known_sigma)
    model.num_timesteps, model._total_timesteps = 1024, 4096  # t/T = 0.25
    assert model.variance_schedule() == pytest.approx(0.25)
    model.train()
    model.logger.dump(step=model.num_timesteps)
    logged = writer.dumps[-1]
    assert logged["train/variance_loss"] == pytest.approx(0.25 * 0.3 * 5.53125, rel=1e-6)
    assert logged["train/variance_schedule"] == pytest.approx(0.25)


def test_variance_loss_shrinks_sigma(small_model, obs_batch) -> None:
    """Same seed, same data: a strong lambda_sigma drives sigma(o) down compared with lambda_sigma = 0."""
    obs = obs_batch(64, seed=11)
    sigmas = {}
    for coef in (0.0, 50.0):
        model = small_model("odv-ppo", seed=5, variance_coef=coef, learning_rate=1e-2)
        model.learn(256)
        sigmas[coef] = model.policy.action_stats(obs)[2].exp().mean().item()
    assert sigmas[50.0] < 0.9 * sigmas[0.0]


def test_schedule_grows_over_the_run(small_model, recorder) -> None:
    model = small_model("odv-ppo")
    writer = recorder(model)
    model.learn(512, log_interval=1)  # 4 updates at t = 128, 256, 384, 512 (dumped before the next update)
    schedules = [d["train/variance_schedule"] for d in writer.dumps if "train/variance_schedule" in d]
    np.testing.assert_allclose(schedules, [0.25, 0.5, 0.75])
    assert model.variance_schedule() == 1.0
    # resuming with the remaining steps keeps T: 512 done + 512 more => T = 1024
    model.learn(512, reset_num_timesteps=False)
    assert model._total_timesteps == 1024 and model.variance_schedule() == 1.0


# ---- NaN / Inf guard -------------------------------------------------------------------------------------------
def test_nan_guard_on_policy_output_names_tensor_and_timestep(small_model) -> None:
    model = small_model("odv-ppo-drop")
    model.learn(128)
    with th.no_grad():
        model.policy.action_net.weight[0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match=r"non-finite value in 'policy\.mean' at timestep 128") as info:
        model.learn(128, reset_num_timesteps=False)
    assert info.value.timestep == 128 and info.value.tensor_name == "policy.mean"


def test_nan_guard_on_loss_names_variance_loss(small_model) -> None:
    model = small_model("odv-ppo")
    model.variance_target = float("inf")  # (sigma^2 - inf)^2 = inf
    with pytest.raises(NonFiniteError, match=r"non-finite value in 'variance_loss' at timestep 128"):
        model.learn(256)


def test_nan_guard_in_training_pass(small_model) -> None:
    model = small_model("ppo")
    model.learn(128)  # fills the rollout buffer
    with th.no_grad():
        model.policy.value_net.bias.fill_(float("inf"))
    with pytest.raises(NonFiniteError, match=r"non-finite value in 'policy\.value' at timestep 128"):
        model.train()  # the update on that buffer


# ---- save / load -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("algo", ["ppo-drop", "odv-ppo-drop"])
def test_save_load_roundtrip(small_model, obs_batch, tmp_path, algo: str) -> None:
    model = small_model(algo, seed=3)
    model.learn(256)
    path = tmp_path / "model.zip"
    model.save(path)
    loaded = ODVPPO.load(path, device="cpu")

    obs = {k: v.numpy() for k, v in obs_batch(32, seed=9).items()}
    a1, _ = model.predict(obs, deterministic=True)
    a2, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(a1, a2)
    for before, after in zip(model.policy.feature_range, loaded.policy.feature_range, strict=True):
        assert th.isfinite(before).all()
        assert th.equal(before, after)
    assert loaded.policy.odv == model.policy.odv and loaded.policy.p_test == 0.5
    assert loaded.policy.dropout_p == pytest.approx(0.1)
    assert loaded.variance_coef == model.variance_coef
    assert loaded.algo_name == algo and loaded.algo_config == model.algo_config


# ---- presets and make_model --------------------------------------------------------------------------------------
@pytest.mark.parametrize("algo", ALGOS)
def test_short_learn_runs_and_logs(small_model, recorder, algo: str) -> None:
    model = small_model(algo)
    writer = recorder(model)
    model.learn(384)
    assert model.num_timesteps == 384
    keys = writer.keys
    assert {"train/policy_gradient_loss", "train/value_loss", "train/std"} <= keys
    assert ("train/variance_loss" in keys) == (algo in ODV_ALGOS)
    assert not model.policy.training  # learn() leaves the policy in eval mode
    if algo == "odv-ppo-noloss":
        assert all(d["train/variance_loss"] == 0.0 for d in writer.dumps if "train/variance_loss" in d)


@pytest.mark.parametrize("verbose", [0, 1])
def test_learn_without_tensorboard_leaves_no_folder_in_the_temp_directory(small_model, monkeypatch, tmp_path, capsys,
                                                                          verbose) -> None:
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.delenv("SB3_LOGDIR", raising=False)
    model = small_model("odv-ppo")
    model.verbose = verbose
    model.learn(128)
    model.learn(128, reset_num_timesteps=False)
    assert model.num_timesteps == 256 and not list(tmp_path.glob("SB3-*"))
    assert ("total_timesteps" in capsys.readouterr().out) == (verbose == 1)  # verbose: SB3's table on stdout


def test_tensorboard_log_contains_variance_loss(small_model, tmp_path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    model = make_model("odv-ppo-drop", small_model("odv-ppo").env, seed=0, tensorboard_log=str(tmp_path),
                       overrides={"n_steps": 32, "batch_size": 64, "n_epochs": 1})
    model.learn(384, tb_log_name="run")
    run_dir = next(tmp_path.iterdir())
    acc = EventAccumulator(str(run_dir))
    acc.Reload()
    assert "train/variance_loss" in acc.Tags()["scalars"]


def test_preset_values() -> None:
    assert set(ALGOS) == {"ppo", "ppo-drop", "odv-ppo-noloss", "odv-ppo", "odv-ppo-drop"}
    for name in ODV_ALGOS:
        cfg = PRESETS[name]
        assert cfg.odv and cfg.learning_rate == 2.5e-4 and cfg.n_steps == 128 and cfg.batch_size == 128
        assert (cfg.log_std_min, cfg.log_std_max) == (-20.0, 0.25) and cfg.p_test == 0.5
        assert cfg.variance_coef == (0.0 if name == "odv-ppo-noloss" else 0.3) and cfg.variance_target == 0.0
    for name in ("ppo", "ppo-drop"):
        cfg = PRESETS[name]
        assert not cfg.odv and cfg.variance_coef == 0.0
        assert (cfg.learning_rate, cfg.n_steps, cfg.batch_size, cfg.n_epochs) == (3e-4, 128, 128, 10)
        assert (cfg.gamma, cfg.gae_lambda, cfg.clip_range, cfg.ent_coef, cfg.vf_coef) == (0.99, 0.95, 0.2, 0.0, 0.5)
    assert {n: PRESETS[n].p_train for n in ALGOS} == {
        "ppo": 0.0, "ppo-drop": 0.1, "odv-ppo-noloss": 0.0, "odv-ppo": 0.0, "odv-ppo-drop": 0.1
    }


def test_make_model_applies_presets_and_overrides(make_vec_env) -> None:
    model = make_model("odv-ppo-drop", make_vec_env(2), seed=1, overrides={"n_epochs": 3, "p_test": 0.3})
    assert model.learning_rate == 2.5e-4 and model.n_steps == 128 and model.batch_size == 128
    assert model.n_epochs == 3 and model.policy.p_test == 0.3 and model.variance_coef == 0.3
    assert model.policy.log_std_max == 0.25 and model.policy.log_std_min == -20.0


def test_make_model_rejects_bad_names_and_values(make_vec_env) -> None:
    env = make_vec_env(2)
    with pytest.raises(ValueError, match=r"unknown algo 'sac'.*ppo, ppo-drop, odv-ppo-noloss, odv-ppo, odv-ppo-drop"):
        make_model("sac", env, seed=0)
    with pytest.raises(ValueError, match=r"unknown override key 'lr'.*allowed keys: .*learning_rate"):
        make_model("ppo", env, seed=0, overrides={"lr": 1e-3})
    with pytest.raises(ValidationError):
        resolve_config("ppo-drop", {"p_train": 1.5})
    with pytest.raises(ValidationError):
        resolve_config("odv-ppo", {"log_std_min": 1.0})


def test_large_batch_overrides_scale_lr() -> None:
    over = large_batch_overrides("odv-ppo-drop", 512)
    assert over == {"batch_size": 512, "learning_rate": pytest.approx(2.5e-4 * math.sqrt(4))}
    assert resolve_config("odv-ppo-drop", over).batch_size == 512
