"""The perturbation registry (`socnav.envs.perturbations.PERTURBATIONS`): one definition per perturbation type that
the env, the specs, the calibration and the report read; and the behaviour shift (another human model)."""

from __future__ import annotations

import re

import numpy as np
import pytest

import socnav
from socnav.config import ConfigError, PerturbationConfig, load_config, perturbation_text
from socnav.envs.perturbations import (
    CALIBRATION_SET,
    DEFAULT_GRIDS,
    PAPER_GRIDS,
    PERTURBATION_FIELDS,
    PERTURBATIONS,
    is_perturbed,
    perturbation_override,
    perturbed_config,
    strength_zero,
)
from socnav.sim.humans import OrcaHumans, SocialForceHumans, human_model_names

WORLD = {"scenario": "position_swap", "n_humans": 1}


def test_every_perturbation_config_field_is_one_registered_perturbation():
    """A config field without a registry entry would be invisible to the studies and the calibration."""
    fields = list(PERTURBATION_FIELDS.values())
    assert len(set(fields)) == len(fields)
    assert set(fields) == set(PerturbationConfig.model_fields)


@pytest.mark.parametrize("name", list(PERTURBATIONS))
def test_a_registered_perturbation_is_complete(name):
    from socnav.paper import labels as report

    p = PERTURBATIONS[name]
    assert p.name == name and p.field in PerturbationConfig.model_fields
    assert p.unperturbed == getattr(PerturbationConfig(), p.field)  # the config default is the unperturbed world
    assert list(p.grid) == sorted(p.grid) and len(p.grid) >= 2
    # the report has its labels and puts it in a Table 3 column (the paper's, pooled, or our own)
    for labels in (report.PERTURBATION_LABELS, report.STRENGTH_LABELS, report.TABLE3_COLUMN_LABELS):
        assert labels[name]
    assert name in report.PERTURBATION_ORDER
    assert (p.pooled or name) in report.PAPER_TABLE3_COLUMNS or name in report.OWN_TABLE3_COLUMNS
    if p.ours:  # beyond the paper: marked as ours, compared with nothing of the paper's
        assert "(ours)" in report.perturbation_label(name) and "(ours)" in report.TABLE3_COLUMN_LABELS[name]
        assert name not in report.PAPER_COLUMN and name not in PAPER_GRIDS
    else:
        assert report.PAPER_COLUMN[name] in report.PAPER_COLUMN_LABELS


@pytest.mark.parametrize("name", list(PERTURBATIONS))
def test_strength_zero_is_the_unperturbed_world_and_every_other_strength_perturbs(name):
    p = PERTURBATIONS[name]
    calm = perturbed_config(WORLD, name, strength_zero(name))
    assert not is_perturbed(calm) and not p.active(calm.perturbation)
    assert calm.perturbation == load_config(WORLD).perturbation
    for strength in [*p.grid[1:], *p.calibration]:
        config = perturbed_config(WORLD, name, strength)
        assert is_perturbed(config) and p.active(config.perturbation), strength
        others = [q.name for q in PERTURBATIONS.values() if q.name != name and q.active(config.perturbation)]
        assert not others, (strength, others)


def test_the_registry_keeps_the_papers_grids_and_calibration_set():
    steps = [round(0.2 * k, 1) for k in range(11)]
    paper = {"observation_noise": steps, "heading_noise": steps, "speed_noise": steps,
             "faster_humans": [float(x) for x in range(1, 9)], "more_humans": [float(x) for x in range(2, 8)]}
    assert paper == PAPER_GRIDS
    assert CALIBRATION_SET == {"observation_noise": [0.5, 1.3], "heading_noise": [0.5, 1.3],
                               "speed_noise": [0.5, 0.9], "faster_humans": [2.5, 5.5], "more_humans": [4.0, 6.0]}
    assert DEFAULT_GRIDS == PAPER_GRIDS  # the behaviour shift is not in the default grids
    assert perturbation_override("more_humans", 2.0) == {} and perturbation_override("more_humans", 5.0) == {
        "total_agents": 5}
    assert perturbation_override("faster_humans", 3) == {"human_speed_factor": 3.0}
    with pytest.raises(ValueError, match="unknown perturbation 'wind'; allowed: observation_noise"):
        perturbation_override("wind", 1.0)


# ------------------------------------------------------------------------------------------------ behaviour shift

def test_behaviour_shift_is_categorical_and_held_out_of_the_calibration():
    shift = PERTURBATIONS["behaviour_shift"]
    assert shift.field == "human_model" and shift.scale == "categorical" and shift.ours
    assert shift.calibration == () and "behaviour_shift" not in CALIBRATION_SET
    assert not shift.default and "behaviour_shift" not in DEFAULT_GRIDS
    assert set(shift.levels) <= set(human_model_names())
    from socnav.experiments.spec import PERTURBATIONS_DESCRIPTION  # the grids' doc names the levels as registered

    assert ", ".join(f"{k + 1} = {level}" for k, level in enumerate(shift.levels)) in PERTURBATIONS_DESCRIPTION
    assert perturbation_override("behaviour_shift", 0) == {"human_model": None}
    assert perturbation_override("behaviour_shift", 1.0) == {"human_model": "social_force"}
    assert perturbation_override("behaviour_shift", 2.0) == {"human_model": "orca"}
    for bad in (0.5, 3.0, -1.0):
        with pytest.raises(ValueError, match="names no level; allowed: 0 \\(unperturbed\\), 1 = social_force"):
            perturbation_override("behaviour_shift", bad)


def test_a_behaviour_shift_to_the_worlds_own_model_is_refused():
    trained_with_social_force = {**WORLD, "humans": {"model": "social_force"}}
    with pytest.raises(ConfigError, match=re.escape("is the world's own humans.model, so nothing shifts")):
        perturbed_config(trained_with_social_force, "behaviour_shift", 1.0)
    shifted = perturbed_config(trained_with_social_force, "behaviour_shift", 2.0)  # social force -> ORCA humans
    assert shifted.perturbation.human_model == "orca" and is_perturbed(shifted)


def test_human_model_field_is_validated_and_left_out_of_default_dumps():
    assert "human_model" not in load_config({}).model_dump()["perturbation"]  # an unshifted world's dump and hash
    with pytest.raises(ConfigError, match=re.escape("perturbation.human_model")):
        load_config({"perturbation": {"human_model": "sfm"}})
    config = load_config({"perturbation": {"human_model": "social_force"}})
    assert config.model_dump()["perturbation"]["human_model"] == "social_force"
    assert load_config(config.model_dump()) == config
    assert perturbation_text(config) == "human_model=social_force"


def _play(config, seed=3, steps=40):
    env = socnav.make_env(config)
    obs, _ = env.reset(seed=seed)
    observations, done = [obs["humans"].copy()], False
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(np.array([1.0, 0.0], np.float32))
        observations.append(obs["humans"].copy())
        if terminated or truncated:
            done = True
            break
    return env, np.stack(observations), done


def test_env_with_the_behaviour_shift_plays_social_force_humans():
    """The shifted world is the world of social force humans, step for step; the trained one has ORCA humans."""
    shifted = perturbed_config(WORLD, "behaviour_shift", 1.0)
    env, played, _ = _play(shifted)
    assert isinstance(env.world.human_model, SocialForceHumans)
    assert env.config.humans.model == "orca"  # the world as trained, with the shift on top
    _, social_force, _ = _play({**WORLD, "humans": {"model": "social_force"}})
    np.testing.assert_array_equal(played, social_force)
    calm_env, calm, _ = _play(perturbed_config(WORLD, "behaviour_shift", 0.0))
    assert isinstance(calm_env.world.human_model, OrcaHumans)
    assert not np.array_equal(calm, played)  # the humans walk otherwise


def test_env_with_the_behaviour_shift_plays_a_whole_episode():
    _, played, done = _play({**WORLD, "perturbation": {"human_model": "social_force"}}, steps=1000)
    assert done and np.isfinite(played).all()
