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
