"""Experiment files: the shipped ones load, budgets override the grid, units expand as planned, and bad files fail
before any work starts with a message naming the field and the allowed values."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from socnav.cli import app
from socnav.experiments.spec import ExperimentError, load_experiment, parse_experiment, plan_units

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "experiments"
ALGOS = ["ppo", "ppo-drop", "odv-ppo-noloss", "odv-ppo", "odv-ppo-drop"]
SCENARIOS = ["circle_interaction", "circle_crossing", "random"]
runner = CliRunner()


def _minimal() -> dict:
    return {
        "name": "tiny",
        "grid": {"algorithms": ["ppo"], "train_scenarios": ["circle_crossing"], "seeds": [0], "timesteps": 1000},
        "evaluation": {"scenarios": ["random"], "episodes": 5},
    }


def _error(data: dict, tmp_path: Path | None = None) -> str:
    with pytest.raises(ExperimentError) as info:
        if tmp_path is None:
            parse_experiment(data, "test")
        else:
            path = tmp_path / "bad.yaml"
            path.write_text(yaml.safe_dump(data))
            load_experiment(path)
    return str(info.value)


def test_table1_budgets_expand_to_the_paper_grid():
    paper = load_experiment(CONFIGS / "table1.yaml", "paper")
    assert paper.grid.algorithms == ALGOS
    assert paper.grid.train_scenarios == SCENARIOS and paper.evaluation.scenarios == SCENARIOS
    assert paper.grid.seeds == list(range(15)) and paper.evaluation.episodes == 200
    units = plan_units(paper)
    trains = [u for u in units if u.kind == "train"]
    evals = [u for u in units if u.kind == "eval"]
    assert len(trains) == 5 * 3 * 15 and len(evals) == 5 * 3 * 15 * 3
    assert all(u.deps == (f"train/{u.params['train_scenario']}/{u.params['algo']}/seed{u.params['train_seed']}",)
               for u in evals)
    assert {u.params["seed"] for u in evals} == {0}  # every policy sees the same test episodes

    quick = load_experiment(CONFIGS / "table1.yaml", "quick")
    # at least 3 seeds, so the bootstrap over seeds of the statistics section means something
    assert quick.budget == "quick" and 3 <= len(quick.grid.seeds) <= 5
    assert quick.grid.timesteps < paper.grid.timesteps and quick.evaluation.episodes < 200
    # The quick budget's training fits a 2-core laptop in about 90 minutes even at 1,000 env-steps/s per process
    # (below the ~1,250 measured for circle crossing): training steps of all units / (2 processes x 1,000 steps/s).
    steps = sum(u.params["timesteps"] for u in plan_units(quick) if u.kind == "train")
    assert steps / (2 * 1000) <= 90 * 60

    grid = load_experiment(CONFIGS / "table1.yaml")
    assert grid.budget is None and grid.grid.timesteps == paper.grid.timesteps


def test_smoke_experiment_is_two_small_trainings():
    smoke = load_experiment(CONFIGS / "smoke.yaml", "quick")
    units = plan_units(smoke)
    assert [u.kind for u in units].count("train") == 2
    assert all(u.params["timesteps"] <= 5000 for u in units if u.kind == "train")


def test_budget_overrides_merge_and_unknown_budget_names_the_allowed_ones():
    data = _minimal()
    data["grid"]["overrides"] = {"n_epochs": 3}
    data["budgets"] = {"small": {"seeds": 2, "timesteps": 10, "episodes": 2, "overrides": {"batch_size": 32},
                                 "eval_scenarios": ["circle_crossing", "random"]}}
    experiment = parse_experiment(data, "test")
    from socnav.experiments.spec import resolve_budget

    small = resolve_budget(experiment, "small")
    assert small.grid.seeds == [0, 1] and small.grid.timesteps == 10 and small.evaluation.episodes == 2
    assert small.grid.overrides == {"n_epochs": 3, "batch_size": 32}
    assert len(plan_units(small)) == 2 + 2 * 2
    with pytest.raises(ExperimentError, match=r"unknown budget 'paper'.*allowed: small"):
        resolve_budget(experiment, "paper")


def test_unknown_algorithm_names_field_and_allowed_values():
    data = _minimal()
    data["grid"]["algorithms"] = ["ppo", "sac"]
    message = _error(data)
    assert "grid.algorithms" in message and "'sac'" in message
    assert all(algo in message for algo in ALGOS)


def test_missing_field_is_named(tmp_path):
    data = _minimal()
    del data["grid"]["timesteps"]
    message = _error(data, tmp_path)
    assert "grid.timesteps" in message and "missing" in message and "bad.yaml" in message


def test_wrong_type_is_named():
    data = _minimal()
    data["grid"]["timesteps"] = "lots"
    message = _error(data)
    assert "grid.timesteps" in message and "integer" in message and "'lots'" in message


def test_unknown_field_suggests_the_nearest_allowed_one():
    data = _minimal()
    data["evaluation"]["episode"] = 3  # typo of episodes
    message = _error(data)
    assert "evaluation.episode" in message and "did you mean episodes?" in message
    data = _minimal()
    data["budgets"] = {"quick": {"timestep": 5}}
    message = _error(data)
    assert "budgets.quick.timestep" in message and "timesteps" in message


@pytest.mark.parametrize("patch, expected", [
    ({"evaluation": {"scenarios": ["mall"]}}, ["evaluation.scenarios", "'mall'", "circle_crossing"]),
    ({"scenario_env": {"mall": {}}}, ["scenario_env", "'mall'", "random"]),
    ({"env": {"n_humans": -1}}, ["n_humans", "circle_crossing"]),
    ({"env": {"humns": 3}}, ["humns", "unknown field", "humans"]),
    ({"grid": {"overrides": {"learning_rat": 0.1}}}, ["learning_rat", "allowed keys", "learning_rate"]),
    ({"grid": {"seeds": 0}}, ["grid.seeds", "[1, 10000]"]),
    ({"grid": {"seeds": [1, 1]}}, ["grid.seeds", "twice"]),
    ({"name": "table 1/x"}, ["name", "letters"]),
    ({"kind": "table9"}, ["kind", "'table9'", "table1"]),
    ({"scenario_env": {"random": {"max_humans": 12}}}, ["max_humans", "same everywhere"]),
])
def test_invalid_values_name_the_problem(patch, expected):
    data = _minimal()
    for key, value in patch.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) and isinstance(data.get(key), dict) else value
    message = _error(data)
    for fragment in expected:
        assert fragment in message, (fragment, message)


def test_algo_override_preset_file_is_inlined(tmp_path):
    (tmp_path / "presets").mkdir()
    (tmp_path / "presets" / "ppo.yaml").write_text("# tuned\nlearning_rate: 0.0001\nn_epochs: 4\n")
    data = _minimal()
    data["grid"]["overrides"] = {"n_epochs": 7, "gamma": 0.95}
    data["grid"]["algo_overrides"] = {"ppo": "presets/ppo.yaml"}
    path = tmp_path / "exp.yaml"
    path.write_text(yaml.safe_dump(data))
    (unit,) = [u for u in plan_units(load_experiment(path)) if u.kind == "train"]
    assert unit.params["overrides"] == {"n_epochs": 4, "gamma": 0.95, "learning_rate": 0.0001}
    data["grid"]["algo_overrides"] = {"ppo": "presets/missing.yaml"}
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ExperimentError, match=re.escape("grid.algo_overrides.ppo: preset file not found")):
        load_experiment(path)


def test_spec_hash_follows_the_parameters():
    first = plan_units(parse_experiment(_minimal()))
    again = plan_units(parse_experiment(_minimal()))
    assert [u.spec_hash for u in first] == [u.spec_hash for u in again]
    data = _minimal()
    data["grid"]["timesteps"] = 2000
    changed = plan_units(parse_experiment(data))
    assert first[0].spec_hash != changed[0].spec_hash
    # The evaluation asks for the same thing; it goes stale through its input (the model's digest, see runner).
    assert first[1].spec_hash == changed[1].spec_hash
    data["evaluation"]["episodes"] = 6
    assert plan_units(parse_experiment(data))[1].spec_hash != first[1].spec_hash


def test_cli_rejects_bad_experiment_before_any_work(tmp_path):
    data = _minimal()
    data["grid"]["algorithms"] = ["ppo-dropout"]
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "runs"
    result = runner.invoke(app, ["run", str(path), "--out", str(out)])
    assert result.exit_code == 2
    assert "grid.algorithms" in result.output and "ppo-drop" in result.output
    assert not out.exists()
    path.write_text("name: x\ngrid: [unclosed\n")
    result = runner.invoke(app, ["run", str(path), "--out", str(out)])
    assert result.exit_code == 2 and "not valid YAML" in result.output and not out.exists()
    result = runner.invoke(app, ["run", str(CONFIGS / "smoke.yaml"), "--budget", "huge", "--out", str(out)])
    assert result.exit_code == 2 and "unknown budget 'huge'" in result.output and "quick" in result.output
    result = runner.invoke(app, ["run", str(CONFIGS / "smoke.yaml"), "--backend", "slurm", "--out", str(out)])
    assert result.exit_code == 2 and "local, ray" in result.output and not out.exists()


# ---- non-finite, absurd and non-integer values ----

def _with(path: str, value: object) -> dict:
    data = _minimal()
    *parents, last = path.split(".")
    node = data
    for part in parents:
        node = node.setdefault(part, {})
    node[last] = value
    return data


@pytest.mark.parametrize(
    "path, value, hint",
    [
        ("grid.timesteps", True, "valid integer"),
        ("grid.timesteps", 1e300, "valid integer"),
        ("grid.timesteps", 10**15, "less than or equal to"),
        ("grid.seeds", [0, True], "valid integer"),
        ("grid.seeds", [2**28], "seeds must lie in [0, 268435455]"),  # socnav.rl.training.MAX_SEED
        ("grid.n_envs", 4.0, "valid integer"),
        ("evaluation.episodes", float("inf"), "valid integer"),
        ("evaluation.seed", 2**62, "less than or equal to"),
        ("study.p_test", float("nan"), "finite"),
        ("study.perturbations", {"heading_noise": [0.0, float("nan")]}, "finite"),
        ("study.k", True, "valid integer"),
    ],
)
def test_non_finite_and_non_integer_values_are_named(path, value, hint):
    message = _error(_with(path, value))
    assert path in message and hint in message


def test_non_finite_and_boolean_values_in_an_experiment_file_are_named(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(_minimal()).replace("episodes: 5", "episodes: 5\n  seed: true")
                    .replace("timesteps: 1000", "timesteps: 1000\n  n_envs: .inf"))
    with pytest.raises(ExperimentError) as error:
        load_experiment(path)
    assert "evaluation.seed: Input should be a valid integer" in str(error.value)
    assert "grid.n_envs: Input should be a valid integer" in str(error.value)


def test_perturbation_strengths_out_of_the_env_range_are_refused_at_load():
    data = {**_minimal(), "kind": "uncertainty", "study": {"perturbations": {"heading_noise": [0.0, 100.0]}}}
    message = _error(data)
    assert "study.perturbations.heading_noise: strength 100.0" in message and "perturbation.heading_noise" in message


@pytest.mark.parametrize("path", ["grid.n_envs", "evaluation.n_envs"])
def test_env_counts_that_cannot_fit_in_memory_are_refused_at_load(path):
    data = _with(path, 10_000_000)
    data["evaluation"]["episodes"] = 10_000_000
    message = _error(data)
    assert f"{path}=10,000,000" in message and "GiB" in message and "use at most" in message


def test_alias_bomb_preset_file_is_refused(tmp_path):
    preset = tmp_path / "preset.yaml"
    preset.write_text("a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "\n".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join([f'*{chr(97 + i)}'] * 10)}]" for i in range(6)))
    data = _minimal()
    data["grid"]["algo_overrides"] = {"ppo": "preset.yaml"}
    path = tmp_path / "exp.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ExperimentError, match=r"grid\.algo_overrides\.ppo: preset file .* is refused: .*alias"):
        load_experiment(path)


def test_training_seed_limit_is_the_trainers():
    from socnav.experiments.spec import TRAIN_SEED_LIMIT
    from socnav.rl.training import MAX_SEED

    assert TRAIN_SEED_LIMIT == MAX_SEED - 1


# ------------------------------------------------------------------------------------------------ Table 3 ablation

def _uncertainty(**safety) -> dict:
    return {"name": "tiny-unc", "kind": "uncertainty", "scenario_env": {"position_swap": {"n_humans": 1}},
            "grid": {"algorithms": ["odv-ppo-drop"], "train_scenarios": ["position_swap"], "seeds": 2,
                     "timesteps": 256},
            "evaluation": {"scenarios": ["position_swap"], "episodes": 3},
            "safety": {"perturbations": {"heading_noise": [0.0, 1.0]}, "sensing": ["perceived", "true"], **safety}}


def test_table3_held_out_seeds_and_one_command_replications():
    quick = load_experiment(CONFIGS / "table3.yaml", "quick")
    fresh = load_experiment(CONFIGS / "table3.yaml", "quick-fresh-episodes")
    seeds = load_experiment(CONFIGS / "table3.yaml", "quick-training-seeds")
    paper = load_experiment(CONFIGS / "table3.yaml", "paper")
    assert quick.evaluation.seed == seeds.evaluation.seed == paper.evaluation.seed == 3_000_000
    assert fresh.evaluation.seed == 4_000_000
    assert seeds.grid.seeds == list(range(100, 120)) and seeds.safety.mc_seed == 100
    assert quick.safety.mc_seed == fresh.safety.mc_seed == 0
    for other in (fresh, seeds):  # otherwise the quick budget
        assert other.safety.perturbations == quick.safety.perturbations
        assert (other.evaluation.episodes, other.safety.repeats, other.safety.calibration_episodes,
                other.grid.timesteps) == (150, 3, 60, 100_000)
    # the held-out ranges touch none of the seeds development looked at (0-999, 100,000-100,449), nor the
    # calibration's (500,000...), nor each other, at the largest budget
    from socnav.envs.perturbations import CALIBRATION_SEED

    def seen(experiment):
        start = experiment.evaluation.seed
        return range(start, start + experiment.safety.repeats * experiment.evaluation.episodes)

    looked = [range(0, 1000), range(100_000, 100_450), range(CALIBRATION_SEED, CALIBRATION_SEED + 11 * 60)]
    for held_out in (seen(paper), seen(quick), seen(fresh)):
        assert all(not set(held_out) & set(r) for r in looked)
    assert not set(seen(paper)) & set(seen(fresh))
    assert quick.safety.ablation == ["proximity-only", "uncertainty-only"]
    assert quick.safety.ablation_sensing_resolved == "true"
    assert quick.safety.tradeoff_budgets == [0.01, 0.02, 0.05, 0.10]
    assert (quick.safety.tradeoff_search, quick.safety.tradeoff_repeats) == ("light", 1)


@pytest.mark.parametrize("budget, expected", [
    ({"eval_seed": -1}, ["budgets.b.eval_seed", "greater than or equal to 0"]),
    ({"eval_seed": 2**31}, ["budgets.b.eval_seed", "less than or equal to 2147483647"]),
    ({"mc_seed": "seven"}, ["budgets.b.mc_seed", "integer"]),
    ({"mc_seed": 5}, ["budget 'b'", "safety.mc_seed 5 is not among grid.seeds [0, 1]"]),
])
def test_budget_evaluation_seed_and_acting_policy_are_validated(budget, expected):
    message = _error({**_uncertainty(), "budgets": {"b": budget}})
    for fragment in expected:
        assert fragment in message, (fragment, message)


def test_budget_evaluation_seed_and_acting_policy_apply():
    from socnav.experiments.spec import resolve_budget

    data = {**_uncertainty(), "study": {"perturbations": {"heading_noise": [0.0, 1.0]}},
            "budgets": {"b": {"seeds": [3, 4], "mc_seed": 4, "eval_seed": 77}}}
    chosen = resolve_budget(parse_experiment(data, "test"), "b")
    assert (chosen.evaluation.seed, chosen.safety.mc_seed, chosen.study.mc_seed) == (77, 4, 4)
    acting = next(u for u in plan_units(chosen) if u.id == "safety/mc/heading_noise")
    assert acting.deps[0] == "train/position_swap/odv-ppo-drop/seed4" and acting.params["seed"] == 77


@pytest.mark.parametrize("safety, expected", [
    ({"ablation": ["paper"]}, ["safety.ablation", "'proximity-only' or 'uncertainty-only'"]),
    ({"ablation": ["proximity-only", "proximity-only"]}, ["safety.ablation", "lists a rule twice"]),
    ({"tradeoff_budgets": [0.1, 0.05]}, ["safety.tradeoff_budgets", "increasing"]),
    ({"tradeoff_budgets": [0.0, 0.05]}, ["safety.tradeoff_budgets", "(0, 1]"]),
    ({"ablation": ["uncertainty-only"], "calibrate": False}, ["safety", "calibrate must be true"]),
    ({"ablation": ["proximity-only"], "ablation_sensing": "true", "sensing": ["perceived"]},
     ["safety", "ablation_sensing 'true' must be one of sensing ['perceived']"]),
    ({"ablation_sensing": "lidar"}, ["safety.ablation_sensing", "'perceived' or 'true'"]),
    ({"tradeoff_search": "quick"}, ["safety.tradeoff_search", "'full' or 'light'"]),
    ({"tradeoff_repeats": 0}, ["safety.tradeoff_repeats", "greater than or equal to 1"]),
])
def test_ablation_fields_name_the_problem(safety, expected):
    message = _error(_uncertainty(**safety))
    for fragment in expected:
        assert fragment in message, (fragment, message)


def test_a_huge_seed_count_is_refused_before_it_is_expanded():
    data = _minimal()
    data["grid"]["seeds"] = 10**8  # list(range(10**8)) would take gigabytes before any check
    message = _error(data)
    assert "grid.seeds" in message and "[1, 10000]" in message and "got 100000000" in message


def test_a_grid_above_the_unit_bound_is_refused_with_its_count(monkeypatch):
    import socnav.experiments.spec as spec

    data = _minimal()
    data["grid"].update(algorithms=ALGOS, train_scenarios=SCENARIOS, seeds=10)
    data["evaluation"]["scenarios"] = SCENARIOS
    experiment = parse_experiment(data, "test")
    assert len(plan_units(experiment)) == spec.planned_unit_count(experiment) == 5 * 3 * 10 * (1 + 3)
    monkeypatch.setattr(spec, "MAX_UNITS", 599)
    built = []
    monkeypatch.setitem(spec.PLANNERS, "table1", lambda e: built.append(e) or [])
    with pytest.raises(ExperimentError, match=r"the grid makes 600 units, above the bound of 599"):
        plan_units(experiment)
    assert built == []  # refused before the planner ran


@pytest.mark.parametrize("name", ["table1", "table2", "table3", "safety_benchmark"])
def test_the_unit_count_bounds_every_shipped_plan(name):
    from socnav.experiments.spec import planned_unit_count

    for budget in [None, *yaml.safe_load((CONFIGS / f"{name}.yaml").read_text()).get("budgets", {})]:
        experiment = load_experiment(CONFIGS / f"{name}.yaml", budget)
        assert len(plan_units(experiment)) <= planned_unit_count(experiment)


@pytest.mark.parametrize("budget", ["../../etc", "a/b", "", "quick fast"])
def test_a_budget_name_that_is_not_a_directory_name_is_refused(budget):
    data = _minimal()
    data["budgets"] = {budget: {"episodes": 3}}
    assert "it names a directory" in _error(data)
