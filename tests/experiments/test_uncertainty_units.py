"""The `uncertainty` experiment kind end to end on a tiny budget: ensemble training, study, calibration, safety."""

import pandas as pd
import pytest

from socnav.experiments.runner import run_experiment
from socnav.experiments.spec import ExperimentError, parse_experiment, plan_units

TINY = {
    "name": "tiny-uncertainty",
    "kind": "uncertainty",
    "scenario_env": {"position_swap": {"n_humans": 1}},
    "grid": {"algorithms": ["odv-ppo-drop"], "train_scenarios": ["position_swap"], "seeds": 2, "timesteps": 256,
             "n_envs": 2, "eval_every": 256, "validation_episodes": 2},
    "evaluation": {"scenarios": ["position_swap"], "episodes": 3, "seed": 0, "n_envs": 3},
    "study": {"perturbations": {"observation_noise": [0.0, 1.0], "more_humans": [2.0, 3.0]}, "k": 4},
    "safety": {"perturbations": {"heading_noise": [0.0, 1.5]}, "repeats": 2, "calibration_episodes": 2, "k": 4},
}


def test_plan_orders_trainings_first_and_wires_dependencies():
    units = {unit.id: unit for unit in plan_units(parse_experiment(TINY))}
    assert units["study/mc/observation_noise"].deps == ("train/position_swap/odv-ppo-drop/seed0",)
    assert len(units["study/ensemble/more_humans"].deps) == 2
    assert units["safety/mc/heading_noise"].deps[-1] == "calibrate/mc"


def test_bad_perturbation_names_are_rejected_before_any_work():
    bad = {**TINY, "study": {"perturbations": {"wind": [0.0, 1.0]}}}
    with pytest.raises(ExperimentError, match="unknown perturbation 'wind'; allowed: observation_noise"):
        parse_experiment(bad)


def test_tiny_uncertainty_experiment_runs_end_to_end(tmp_path):
    summary = run_experiment(parse_experiment(TINY), tmp_path, workers=0)
    assert summary.ok, [outcome.error for outcome in summary.failed]
    steps = pd.read_parquet(tmp_path / "study" / "ensemble" / "more_humans" / "steps.parquet")
    episodes = pd.read_parquet(tmp_path / "study" / "ensemble" / "more_humans" / "episodes.parquet")
    assert set(steps["strength"]) == {2.0, 3.0} and len(episodes) == 6
    assert len(steps) == episodes["length"].sum()
    assert (steps[["u_ep_heading", "u_al_speed", "u_feat"]] >= 0).all().all()
    safety = pd.read_parquet(tmp_path / "safety" / "mc" / "heading_noise" / "episodes.parquet")
    assert set(safety["variant"]) == {"none", "paper", "calibrated"}
    per_block = safety.groupby(["strength", "repeat", "variant"])["seed"].apply(lambda s: tuple(sorted(s)))
    for (strength, repeat), block in per_block.groupby(level=[0, 1]):
        assert len(set(block)) == 1  # every variant played the same episode seeds
    assert (safety.loc[safety["variant"] == "none", "fallback_steps"] == 0).all()
    assert (tmp_path / "calibrate" / "mc" / "thresholds.yaml").is_file()


def test_both_sensings_are_calibrated_and_evaluated(tmp_path):
    from socnav.experiments.report import build_report

    safety = {"estimators": ["mc"], "perturbations": {"observation_noise": [0.0, 1.5]}, "repeats": 1, "k": 4,
              "sensing": ["perceived", True]}  # an unquoted YAML `true` is a boolean
    spec = {**TINY, "name": "tiny-sensing", "grid": {**TINY["grid"], "seeds": 1}, "study": None, "safety": safety}
    units = {unit.id: unit for unit in plan_units(parse_experiment(spec))}
    assert (units["calibrate/mc"].params["sensing"], units["calibrate-true/mc"].params["sensing"]) == \
        ("perceived", "true")
    assert units["safety/mc/observation_noise"].deps[-2:] == ("calibrate/mc", "calibrate-true/mc")
    # the run itself without the (slow) calibration: the paper thresholds with each sensing
    spec["safety"] = {**safety, "calibrate": False}
    summary = run_experiment(parse_experiment(spec), tmp_path, workers=0)
    assert summary.ok, [outcome.error for outcome in summary.failed]
    records = pd.read_parquet(tmp_path / "safety" / "mc" / "observation_noise" / "episodes.parquet")
    pairs = set(records[["variant", "sensing"]].itertuples(index=False, name=None))
    assert pairs == {("none", ""), ("paper", "perceived"), ("paper", "true")}
    # without noise (strength 0) the true state is the observation: both sensings play the same episodes
    calm = records[(records["strength"] == 0.0) & (records["variant"] == "paper")]
    by_sensing = [g.sort_values("seed")[["seed", "outcome", "length", "fallback_steps"]].reset_index(drop=True)
                  for _, g in calm.groupby("sensing")]
    assert by_sensing[0].equals(by_sensing[1])
    assert "paper thresholds, true state" in build_report(tmp_path).read_text()


def test_sensing_choices_are_validated():
    for bad, message in (([], "at least one of: perceived, true"), (["true", "true"], "lists a sensing twice"),
                         (["lidar"], "'perceived' or 'true'")):
        with pytest.raises(ExperimentError, match=message):
            parse_experiment({**TINY, "safety": {**TINY["safety"], "sensing": bad}})
    single = parse_experiment({**TINY, "safety": {**TINY["safety"], "sensing": "true"}})
    assert single.safety.sensing == ["true"]
    assert parse_experiment(TINY).safety.sensing == ["perceived"]  # the default: as before the choice existed
