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
    for _, block in per_block.groupby(level=[0, 1]):
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
    assert parse_experiment(TINY).safety.sensing == ["perceived"]  # the default: the layer reads the observation


ABLATION = {**TINY, "name": "tiny-ablation", "grid": {**TINY["grid"], "seeds": 1}, "study": None,
            "safety": {"estimators": ["mc"], "perturbations": {"observation_noise": [0.0, 1.5]}, "repeats": 1, "k": 4,
                       "calibration_episodes": 2, "sensing": ["perceived", "true"],
                       "ablation": ["proximity-only", "uncertainty-only"], "tradeoff_budgets": [0.02, 0.05]}}


def test_ablation_plans_one_proximity_only_calibration_and_per_estimator_rows():
    perturbations = {"observation_noise": [0.0, 1.5], "more_humans": [2.0, 3.0]}
    plan = plan_units(parse_experiment({**ABLATION, "grid": {**TINY["grid"], "seeds": 2},
                                        "safety": {**ABLATION["safety"], "estimators": ["mc", "ensemble"],
                                                   "perturbations": perturbations}}))
    units = {unit.id: unit for unit in plan}
    acting = "train/position_swap/odv-ppo-drop/seed0"
    proximity = units["calibrate-true/proximity-only"]
    assert proximity.deps == (acting,)  # reads no uncertainty: the acting policy only, once for all estimators
    assert (proximity.params["conditions"], proximity.params["estimator"], proximity.params["tradeoff_budgets"]) == \
        ("proximity-only", None, [0.02])
    # the paper's rule of the ablation's sensing also at the trade-off budgets; the other sensing as before
    assert units["calibrate-true/ensemble"].params["tradeoff_budgets"] == [0.02]
    assert "tradeoff_budgets" not in units["calibrate/ensemble"].params
    assert "conditions" not in units["calibrate-true/ensemble"].params
    uncertainty = units["calibrate-true/ensemble-uncertainty-only"]
    assert uncertainty.params["conditions"] == "uncertainty-only" and len(uncertainty.deps) == 2
    safety = units["safety/ensemble/observation_noise"]
    assert safety.deps[-3:] == ("calibrate/ensemble", "calibrate-true/ensemble",
                                "calibrate-true/ensemble-uncertainty-only")
    assert safety.params["ablation"] == {"sensing": "true", "budget": 0.05, "rules": ["uncertainty-only"],
                                         "tradeoff_budgets": [0.02], "tradeoff_repeats": None, "unperturbed": True}
    rule = units["safety/none/observation_noise"]
    assert rule.kind == "safety_eval_proximity" and rule.deps == (acting, proximity.id)
    assert rule.params["budgets"] == [0.05, 0.02] and rule.params["seed"] == safety.params["seed"]
    # the unperturbed strength is the same world in every unit: only the first perturbation type plays it
    assert rule.params["unperturbed"] and not units["safety/none/more_humans"].params["unperturbed"]
    assert not units["safety/mc/more_humans"].params["ablation"]["unperturbed"]
    # every calibration before the first evaluation, the longest first: the runner starts ready units in plan order
    kinds = [unit.kind for unit in plan if unit.kind != "train"]
    assert kinds == sorted(kinds, key=lambda kind: kind != "calibrate")
    assert [unit.id for unit in plan if unit.kind == "calibrate"][:2] == ["calibrate-true/ensemble",
                                                                           "calibrate-true/mc"]
    assert [unit.id for unit in plan if unit.kind == "calibrate"][-1] == "calibrate-true/proximity-only"
    # a lighter search and fewer repeats for the trade-off budgets, when asked
    light = {unit.id: unit for unit in plan_units(parse_experiment({**ABLATION, "safety": {
        **ABLATION["safety"], "tradeoff_search": "light", "tradeoff_repeats": 1}}))}
    assert light["calibrate-true/mc"].params["tradeoff_search"] == "light"
    assert "tradeoff_search" not in units["calibrate-true/mc"].params
    assert light["safety/mc/observation_noise"].params["ablation"]["tradeoff_repeats"] == 1
    assert light["safety/none/observation_noise"].params["tradeoff_repeats"] == 1


def test_without_ablation_the_plan_is_what_it_was():
    plain = {unit.id: unit for unit in plan_units(parse_experiment(TINY))}
    assert "ablation" not in plain["safety/mc/heading_noise"].params
    assert not any(uid.startswith(("safety/none", "calibrate-true/proximity")) for uid in plain)
    # without the ablation, the paper's rule alone: these spec hashes keep such runs' finished units done
    assert plain["calibrate/mc"].spec_hash == "63376c4570c8a55762d1b23310d53a0b123fd8e69ed0a1a9d40f17b07bf575ed"


def _planted(root, units):
    """A run directory with the shipped policy as the trained one and hand-written calibrated thresholds: the
    safety executors only read them. The gated rule of the true sensing fires on any uncertainty, so it hands over
    where the proximity-only rule with the same gate does."""
    import shutil

    from socnav.experiments.registry import unit_dir
    from socnav.rl.persistence import pretrained_path
    from socnav.safety import Thresholds, save_thresholds

    model = unit_dir(root, "train/position_swap/odv-ppo-drop/seed0") / "model.zip"
    model.parent.mkdir(parents=True)
    shutil.copy(pretrained_path(), model)
    gate = {"lambda_prox": 1.5, "beta1": 0.5, "proximity": "closing-speed", "hold_steps": 1}
    files = {("calibrate/mc", "thresholds.yaml"): {"lambda_ep": 0.05, "lambda_feat": 0.3, **gate},
             ("calibrate-true/mc", "thresholds.yaml"): {"lambda_ep": 0.0, "lambda_feat": 0.0, **gate},
             ("calibrate-true/mc", "thresholds-budget0.02.yaml"): {"lambda_ep": 0.2, "lambda_feat": 0.5, **gate},
             ("calibrate-true/mc-uncertainty-only", "thresholds.yaml"): {
                 "lambda_ep": 0.05, "lambda_feat": 0.3, "lambda_prox": 1000.0, "beta1": 0.0,
                 "conditions": "uncertainty-only"},
             ("calibrate-true/proximity-only", "thresholds.yaml"): {
                 "lambda_ep": 0.0, "lambda_feat": 0.0, **gate, "conditions": "proximity-only"},
             ("calibrate-true/proximity-only", "thresholds-budget0.02.yaml"): {
                 "lambda_ep": 0.0, "lambda_feat": 0.0, **gate, "lambda_prox": 0.5, "conditions": "proximity-only"}}
    for (unit, name), fields in files.items():
        save_thresholds(Thresholds.create(fields), unit_dir(root, unit) / name)
    for uid in ("safety/mc/observation_noise", "safety/none/observation_noise"):
        from socnav.experiments.registry import EXECUTORS

        directory = unit_dir(root, uid)
        directory.mkdir(parents=True)
        EXECUTORS[units[uid].kind](root, units[uid], directory)
    return (pd.read_parquet(unit_dir(root, "safety/mc/observation_noise") / "episodes.parquet"),
            pd.read_parquet(unit_dir(root, "safety/none/observation_noise") / "episodes.parquet"))


def test_ablation_safety_units_play_every_rule_on_the_same_episodes(tmp_path):
    units = {unit.id: unit for unit in plan_units(parse_experiment(ABLATION))}
    gated, proximity = _planted(tmp_path, units)
    rows = set(gated[["variant", "sensing", "rule"]].itertuples(index=False, name=None))
    assert rows == {("none", "", ""), ("paper", "perceived", "paper"), ("paper", "true", "paper"),
                    ("calibrated", "perceived", "paper"), ("calibrated", "true", "paper"),
                    ("calibrated", "true", "uncertainty-only")}
    budgets = gated[gated["variant"] == "calibrated"].groupby(["sensing", "rule"])["budget"].apply(set).to_dict()
    assert budgets == {("perceived", "paper"): {0.05}, ("true", "paper"): {0.02, 0.05},
                       ("true", "uncertainty-only"): {0.05}}
    assert set(proximity[["estimator", "variant", "rule"]].itertuples(index=False, name=None)) == {
        ("none", "none", ""), ("none", "calibrated", "proximity-only")}
    assert set(proximity["budget"].dropna()) == {0.02, 0.05} and set(proximity["sensing"]) == {"", "true"}
    # both units played the plain policy on the same episodes, and so every rule
    key = ["strength", "repeat", "seed"]
    plain = [frame[frame["variant"] == "none"].sort_values(key)[[*key, "outcome", "length"]].reset_index(drop=True)
             for frame in (gated, proximity)]
    pd.testing.assert_frame_equal(plain[0], plain[1])
    for frame in (gated, proximity):
        assert (frame.groupby(["variant", "sensing", "rule", "budget"], dropna=False)["seed"].apply(
            lambda s: tuple(sorted(s))).nunique()) == 1
    # the gated rule that fires on any uncertainty hands over wherever proximity-only with its gate does
    same = [frame[(frame["variant"] == "calibrated") & (frame["sensing"] == "true") & (frame["budget"] == 0.05)
                  & frame["rule"].isin(["paper", "proximity-only"])].sort_values(key).reset_index(drop=True)
            for frame in (gated, proximity)]
    assert (same[0]["fallback_steps"] > 0).any()
    assert same[0]["fallback_digest"].tolist() == same[1]["fallback_digest"].tolist()
    assert (same[0]["vetoed_steps"] == 0).all()  # the uncertainty condition vetoed nothing
    assert (proximity["vetoed_steps"] == 0).all()  # a rule without uncertainty condition vetoes nothing
    # a stricter uncertainty gate (budget 2 %) holds some of those hand-overs back
    strict = gated[(gated["rule"] == "paper") & (gated["budget"] == 0.02)]
    assert strict["vetoed_steps"].sum() > 0


def test_proximity_only_calibration_unit_writes_every_budget_without_an_estimator(tmp_path, monkeypatch):
    import json

    import socnav.paper.uncertainty.units as units_module
    from socnav.experiments.registry import EXECUTORS, unit_dir
    from socnav.safety import load_thresholds

    monkeypatch.setattr(units_module, "build_estimator",
                        lambda *a, **k: pytest.fail("proximity-only built an estimator"))
    units = {unit.id: unit for unit in plan_units(parse_experiment(ABLATION))}
    _planted_policy = tmp_path / "train" / "position_swap" / "odv-ppo-drop" / "seed0" / "model.zip"
    _planted_policy.parent.mkdir(parents=True)
    from socnav.rl.persistence import pretrained_path

    _planted_policy.write_bytes(pretrained_path().read_bytes())
    unit = units["calibrate-true/proximity-only"]
    directory = unit_dir(tmp_path, unit)
    directory.mkdir(parents=True)
    result = EXECUTORS["calibrate"](tmp_path, unit, directory)
    assert result.outputs == ["thresholds.yaml", "calibration.json", "thresholds-budget0.02.yaml",
                              "calibration-budget0.02.json"]
    for name in ("calibration.json", "calibration-budget0.02.json"):
        report = json.loads((directory / name).read_text())
        assert (report["estimator"], report["conditions"], report["sensing"]) == ("none", "proximity-only", "true")
    assert json.loads((directory / "calibration-budget0.02.json").read_text())["false_activation_budget"] == 0.02
    assert load_thresholds(directory / "thresholds.yaml").sensing == "true"


def test_with_the_ablation_only_one_unit_plays_the_unperturbed_world():
    from socnav.paper.uncertainty.units import play_safety_episodes
    from socnav.rl.persistence import load_policy

    policy = load_policy("pretrained")
    p = {"env": {"scenario": "position_swap", "n_humans": 1}, "perturbation": "faster_humans",
         "strengths": [1.0, 4.0], "repeats": 1, "episodes": 2, "seed": 0, "n_envs": 2, "window": 4}
    first = play_safety_episodes(p, policy, [], lambda _: None, {"estimator": "mc"}, ablation=True, unperturbed=True)
    other = play_safety_episodes(p, policy, [], lambda _: None, {"estimator": "mc"}, ablation=True, unperturbed=False)
    assert set(first["strength"]) == {1.0, 4.0} and set(other["strength"]) == {4.0}
    pd.testing.assert_frame_equal(first[first["strength"] == 4.0].reset_index(drop=True), other)
    assert set(first["rule"]) == {""} and first["budget"].isna().all()  # the plain policy's ablation tags


def test_a_trade_off_budget_plays_only_its_first_repeats():
    from socnav.paper.uncertainty.units import SafetyVariant, play_safety_episodes
    from socnav.rl.persistence import load_policy
    from socnav.safety import Thresholds

    gate = {"lambda_ep": 0.0, "lambda_feat": 0.0, "lambda_prox": 1.0, "beta1": 0.0, "conditions": "proximity-only"}
    variants = [SafetyVariant("calibrated", Thresholds.create(gate), "proximity-only", 0.05),
                SafetyVariant("calibrated", Thresholds.create(gate, lambda_prox=0.5), "proximity-only", 0.1, repeats=1)]
    p = {"env": {"scenario": "position_swap", "n_humans": 1}, "perturbation": "faster_humans", "strengths": [4.0],
         "repeats": 2, "episodes": 2, "seed": 0, "n_envs": 2, "window": 4}
    records = play_safety_episodes(p, load_policy("pretrained"), variants, lambda _: None, {"estimator": "none"},
                                   ablation=True)
    repeats = records.groupby("budget", dropna=False)["repeat"].apply(set).to_dict()
    assert repeats[0.05] == {0, 1} and repeats[0.1] == {0}  # the trade-off budget: the first repeat only


# ------------------------------------------------------------------------------------------------ behaviour shift

SHIFT = {**TINY, "name": "tiny-behaviour-shift", "grid": {**TINY["grid"], "seeds": 1},
         "study": {"estimators": ["mc"], "perturbations": {"behaviour_shift": [0, 1]}, "k": 4},
         "safety": {"estimators": ["mc"], "perturbations": {"behaviour_shift": [0, 1]}, "repeats": 1,
                    "calibration_episodes": 2, "k": 4}}


def test_behaviour_shift_grids_are_validated_and_not_a_default():
    from socnav.experiments.spec import Safety, Study

    assert "behaviour_shift" not in Study().perturbations and "behaviour_shift" not in Safety().perturbations
    for bad in ([0, 0.5], [0, 3]):
        with pytest.raises(ExperimentError, match=r"behaviour_shift: strength .* names no level"):
            parse_experiment({**SHIFT, "study": {"perturbations": {"behaviour_shift": bad}}})
    # a world whose humans already walk by social force: strength 1 (social force) would shift nothing
    same = {**SHIFT, "env": {"humans": {"model": "social_force"}}}
    with pytest.raises(ExperimentError, match=r"strength 1.0 gives an invalid env:\n.*so nothing shifts"):
        parse_experiment(same)
    # the calibration unit is the same with or without a behaviour shift column: it never sees the shift
    plain = {**SHIFT, "safety": {**SHIFT["safety"], "perturbations": {"heading_noise": [0.0, 1.5]}}}
    calibrations = [{unit.id: unit for unit in plan_units(parse_experiment(spec))}["calibrate/mc"]
                    for spec in (SHIFT, plain)]
    assert calibrations[0].spec_hash == calibrations[1].spec_hash


def test_a_tiny_behaviour_shift_experiment_runs_with_social_force_humans(tmp_path):
    """Trained with ORCA humans, studied and evaluated (paper thresholds) with social force humans at strength 1."""
    from socnav.experiments.report import build_report

    spec = {**SHIFT, "safety": {**SHIFT["safety"], "calibrate": False}}
    units = {unit.id: unit for unit in plan_units(parse_experiment(spec))}
    assert {"study/mc/behaviour_shift", "safety/mc/behaviour_shift"} <= set(units)
    summary = run_experiment(parse_experiment(spec), tmp_path, workers=0)
    assert summary.ok, [outcome.error for outcome in summary.failed]
    steps = pd.read_parquet(tmp_path / "study" / "mc" / "behaviour_shift" / "steps.parquet")
    episodes = pd.read_parquet(tmp_path / "study" / "mc" / "behaviour_shift" / "episodes.parquet")
    assert set(steps["strength"]) == {0.0, 1.0} and len(episodes) == 6 and len(steps) == episodes["length"].sum()
    safety = pd.read_parquet(tmp_path / "safety" / "mc" / "behaviour_shift" / "episodes.parquet")
    assert set(safety["variant"]) == {"none", "paper"} and set(safety["strength"]) == {0.0, 1.0}
    text = build_report(tmp_path).read_text()
    assert "Behaviour shift (ours): MC" in text and "| Behaviour shift (ours) |" in text
