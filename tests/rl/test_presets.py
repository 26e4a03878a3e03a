"""Hyperparameters: every override is finite, in a meaningful range and of the right type, or refused by name."""

from __future__ import annotations

import math

import pytest

from socnav.rl.presets import ALGOS, AlgoConfig, resolve_config


def _float_fields() -> list[str]:
    """The float hyperparameters, read off AlgoConfig (a field added later is covered too)."""
    return [name for name, info in AlgoConfig.model_fields.items() if info.annotation in (float, float | None)]


def test_float_fields_are_found():
    assert {"learning_rate", "gamma", "clip_range", "ent_coef", "log_std_max", "target_kl"} <= set(_float_fields())


@pytest.mark.parametrize("field", _float_fields())
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
def test_non_finite_hyperparameters_are_refused_by_name(field, bad):
    with pytest.raises(ValueError, match=rf"{field}\n.*finite number"):
        resolve_config("ppo", {field: bad})


@pytest.mark.parametrize(
    "overrides, field, hint",
    [
        ({"n_steps": True}, "n_steps", "valid integer"),
        ({"batch_size": 64.0}, "batch_size", "valid integer"),
        ({"net_arch_pi": [64, True]}, "net_arch_pi.1", "valid integer"),
        ({"net_arch_vf": [10**9]}, "net_arch_vf.0", "less than or equal to 4096"),  # 10^9-wide layer: 8 TB
        ({"lstm_hidden_size": 10**7}, "lstm_hidden_size", "less than or equal to"),
        ({"learning_rate": 1e300}, "learning_rate", "less than or equal to 1"),
        ({"clip_range": 50.0}, "clip_range", "less than or equal to 1"),
    ],
)
def test_absurd_hyperparameters_are_refused_by_name(overrides, field, hint):
    with pytest.raises(ValueError, match=rf"{field}\n.*{hint}"):
        resolve_config("ppo", overrides)


def test_presets_still_validate():
    for algo in ALGOS:
        assert resolve_config(algo) == resolve_config(algo, {})


def test_renamed_dropout_key_points_to_p_train():
    with pytest.raises(ValueError, match=r"'dropout_p'.*renamed p_train.*write p_train"):
        resolve_config("ppo-drop", {"dropout_p": 0.1})


def test_override_errors_read_through_the_one_formatter():
    from socnav.rl.presets import describe_override_error

    with pytest.raises(ValueError) as error:  # pydantic's ValidationError, unchanged for Python callers
        resolve_config("ppo", {"p_train": 1.5, "net_arch_pi": [64, True]})
    lines = describe_override_error("ppo", error.value).splitlines()
    assert lines[0] == "invalid hyperparameters for algo 'ppo':"
    assert "  - p_train: Input should be less than 1 (got 1.5)" in lines
    assert "  - net_arch_pi.1: Input should be a valid integer (got True)" in lines
    with pytest.raises(ValueError) as error:
        resolve_config("ppo", {"lr": 1e-3})
    assert describe_override_error("ppo", error.value) == str(error.value)  # socnav's own message as it is


def test_make_model_takes_an_already_resolved_config():
    import socnav
    from socnav.rl.presets import make_model

    env = socnav.make_vec_env({"scenario": "position_swap", "n_humans": 1}, n_envs=2)
    config = resolve_config("ppo-drop", {"n_steps": 64})
    model = make_model("ppo-drop", env, seed=0, algo_config=config)
    assert model.n_steps == 64 and model.algo_config == config.model_dump(mode="json")
    with pytest.raises(ValueError, match="not both"):
        make_model("ppo-drop", env, seed=0, overrides={"n_steps": 64}, algo_config=config)
