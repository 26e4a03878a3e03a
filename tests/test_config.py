"""Config validation: partial dicts and YAML take defaults; bad fields fail naming the field and what is allowed."""

import pytest

import socnav
from socnav.config import ConfigError, EnvConfig, load_config


def test_partial_dict_takes_defaults():
    config = load_config({"scenario": "circle_crossing"})
    assert config.time_step == 0.25 and config.orca.time_horizon == 5.0 and config.reward.goal == 5.0
    assert config.humans_range() == (5, 5)
    assert socnav.make_env({"scenario": "circle_crossing"}).config == config


def test_yaml_round_trip(tmp_path):
    path = tmp_path / "env.yaml"
    path.write_text("scenario: position_swap\nreward:\n  goal: 3.0\nperturbation:\n  speed_noise: 0.4\n")
    config = load_config(path)
    assert (config.scenario, config.reward.goal, config.perturbation.speed_noise) == ("position_swap", 3.0, 0.4)
    assert load_config(config.model_dump()) == config


@pytest.mark.parametrize(
    "data, field, hint",
    [
        ({"scenaro": "random"}, "scenaro", "did you mean scenario?"),
        ({"zzzz": 1}, "zzzz", "allowed fields here: scenario, n_humans"),
        ({"scenario": "corridor"}, "scenario", "allowed: circle_crossing"),
        ({"time_step": "fast"}, "time_step", "valid number"),
        ({"time_step": -1}, "time_step", "greater than or equal to 0.01"),
        ({"reward": {"gaol": 1}}, "reward.gaol", "did you mean goal?"),
        ({"perturbation": {"speed_noise": -0.5}}, "perturbation.speed_noise", "greater than or equal to 0"),
        ({"inattentive_share": 1.5}, "inattentive_share", "less than or equal to 1"),
        ({"human_fov_deg": 0}, "human_fov_deg", "greater than 0"),
        ({"cooperation": [0.6, 0.2]}, "cooperation", "lower bound"),
        ({"n_humans": 12}, "max_humans", "raise max_humans"),
    ],
)
def test_bad_config_names_the_field(data, field, hint):
    with pytest.raises(ConfigError) as error:
        load_config(data)
    message = str(error.value)
    assert field in message and hint in message


def test_bad_yaml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("scenario: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    listing = tmp_path / "list.yaml"
    listing.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(listing)


def test_overrides_merge_nested():
    config = load_config({"reward": {"goal": 2.0}}, reward={"collision": 9.0})
    assert (config.reward.goal, config.reward.collision) == (2.0, 9.0)
    assert isinstance(config, EnvConfig)
