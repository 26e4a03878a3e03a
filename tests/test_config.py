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
        ({"zzzz": 1}, "zzzz", "allowed fields: scenario, n_humans"),
        ({"scenario": "hallway"}, "scenario", "allowed: circle_crossing"),
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


# ---- non-finite and absurd values ----

def _numeric_fields(model: type = EnvConfig, prefix: str = "") -> list[tuple[str, bool]]:
    """Every float field of the config (dotted path, is it a [min, max] range), read off the models themselves,
    so a numeric field added later is covered without editing this test."""
    from pydantic import BaseModel

    fields = []
    for name, info in model.model_fields.items():
        annotation = info.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            fields += _numeric_fields(annotation, f"{prefix}{name}.")
        elif annotation is float:
            fields.append((prefix + name, False))
        elif getattr(annotation, "__args__", None) == (float, float):
            fields.append((prefix + name, True))
    return fields


def _nested(path: str, value: object) -> dict:
    head, _, rest = path.partition(".")
    return {head: _nested(rest, value) if rest else value}


def test_every_numeric_field_is_found():
    found = dict(_numeric_fields())
    assert {"time_step", "human_radius", "square_size", "circle_radius", "timeout_factor", "perturbation.heading_noise",
            "perturbation.observation_noise", "perturbation.human_speed_factor", "reward.goal",
            "orca.time_horizon"} <= set(found)
    assert found["preferred_speed"] and found["personal_space"] and found["cooperation"]


@pytest.mark.parametrize("path, is_range", _numeric_fields())
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")], ids=["nan", "inf", "-inf"])
def test_non_finite_numbers_are_rejected_naming_the_field(path, is_range, bad):
    value = [0.1, bad] if is_range else bad
    with pytest.raises(ConfigError) as error:
        load_config(_nested(path, value))
    assert path in str(error.value) and "finite" in str(error.value)


def test_non_finite_numbers_in_a_yaml_file_are_rejected(tmp_path):
    path = tmp_path / "env.yaml"
    for text, field in [("preferred_speed: [.nan, 1.0]", "preferred_speed"), ("square_size: .inf", "square_size"),
                        ("perturbation: {heading_noise: .inf}", "perturbation.heading_noise"),
                        ("human_radius: .inf", "human_radius")]:
        path.write_text(text + "\n")
        with pytest.raises(ConfigError, match=field.replace(".", r"\.") + ".*finite"):
            load_config(path)


@pytest.mark.parametrize(
    "data, field",
    [
        ({"time_step": 1e-300}, "time_step"),  # hung the simulation: 10^300 steps per second
        ({"timeout_factor": 1e300}, "timeout_factor"),
        ({"human_radius": 1e300}, "human_radius"),
        ({"square_size": 1e12}, "square_size"),
        ({"preferred_speed": [0.5, 1e9]}, "preferred_speed"),
        ({"personal_space": [0.3, 1e9]}, "personal_space"),
        ({"perturbation": {"human_speed_factor": 1e6}}, "perturbation.human_speed_factor"),
        ({"perturbation": {"observation_noise": 1e6}}, "perturbation.observation_noise"),
        ({"reward": {"collision": 1e300}}, "reward.collision"),
        ({"orca": {"time_horizon": 1e300}}, "orca.time_horizon"),
    ],
)
def test_absurd_magnitudes_are_rejected_naming_the_field(data, field):
    bound = "(Input should be (less|greater) than|bounds must lie in)"
    with pytest.raises(ConfigError, match=field.replace(".", r"\.") + ": " + bound):
        load_config(data)


@pytest.mark.parametrize(
    "data, field",
    [
        ({"n_humans": True}, "n_humans"),
        ({"n_humans": [1, True]}, "n_humans"),
        ({"n_humans": 2.5}, "n_humans"),
        ({"max_humans": True}, "max_humans"),
        ({"orca": {"max_neighbors": False}}, "orca.max_neighbors"),
        ({"perturbation": {"total_agents": True}}, "perturbation.total_agents"),
    ],
)
def test_counts_are_strict_integers(data, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.") + r"\S*: Input should be a valid integer"):
        load_config(data)
    assert load_config({"n_humans": [1, 3]}).n_humans == (1, 3)


# ---- YAML alias bombs and huge inputs ----

BOMB = "\n".join(
    ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    + [f"{b}: &{b} [{','.join([f'*{a}'] * 9)}]" for a, b in zip("abcdefgh", "bcdefghi", strict=True)]
) + "\n"


def test_alias_bomb_is_refused_in_bounded_memory_and_time(tmp_path):
    """Every YAML reader of socnav refuses a 400-byte billion-laughs file, in a child process whose memory growth
    and time are measured (the unbounded reader built a ~1 GB error message)."""
    import subprocess
    import sys
    import textwrap

    assert len(BOMB) < 500
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(BOMB)
    (tmp_path / "thresholds.yaml").write_text(BOMB)
    experiment = tmp_path / "experiment.yaml"
    experiment.write_text("name: x\n" + BOMB)
    script = textwrap.dedent(f"""
        import resource, time
        from socnav.config import ConfigError, load_config
        from socnav.experiments.spec import ExperimentError, load_experiment
        from socnav.safety.rule import ThresholdsError, load_thresholds
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        started = time.perf_counter()
        for load, path, error in [(load_config, {str(bomb)!r}, ConfigError),
                                  (load_experiment, {str(experiment)!r}, ExperimentError),
                                  (load_thresholds, {str(tmp_path / "thresholds.yaml")!r}, ThresholdsError)]:
            try:
                load(path)
            except error as exc:
                assert "alias" in str(exc) and len(str(exc)) < 1000, str(exc)[:300]
            else:
                raise AssertionError(f"{{load.__name__}} accepted the bomb")
        grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
        print(f"grown_kb={{grown}} seconds={{time.perf_counter() - started:.2f}}")
        assert grown < 50_000 and time.perf_counter() - started < 5
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr[-2000:]


def test_cli_yaml_inputs_refuse_the_bomb(tmp_path):
    from typer.testing import CliRunner

    from socnav.cli import app

    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(BOMB)
    result = CliRunner().invoke(app, ["train", "--algo-config", str(bomb), "--out", str(tmp_path / "run")])
    assert result.exit_code == 2 and "alias" in result.output and not (tmp_path / "run").exists()
    result = CliRunner().invoke(app, ["train", "--set", "n_steps=[unclosed", "--out", str(tmp_path / "run")])
    assert result.exit_code == 2 and "--set" in result.output and "not valid YAML" in result.output


def test_bounded_yaml_loader_keeps_ordinary_yaml_and_refuses_recursion():
    from socnav.config import YAML_MAX_NODES, YAMLTooLargeError, safe_load_yaml

    merged = safe_load_yaml("base: &base {goal: 1.0, time: 0.5}\nreward: {<<: *base, goal: 3.0}\n")
    assert merged["reward"] == {"goal": 3.0, "time": 0.5}
    items = YAML_MAX_NODES // 20  # aliases that stay under the bound load as usual
    assert len(safe_load_yaml(f"a: &a [{', '.join(['1'] * 9)}]\nb: [{', '.join(['*a'] * items)}]\n")["b"]) == items
    with pytest.raises(YAMLTooLargeError, match="recursive"):
        safe_load_yaml("a: &a [1, *a]\n")
    with pytest.raises(YAMLTooLargeError, match="nested too deeply"):
        safe_load_yaml("[" * 100_000 + "]" * 100_000)
    with pytest.raises(YAMLTooLargeError, match="characters"):
        safe_load_yaml("x" * (2 << 20))


def test_error_messages_stay_short_for_huge_inputs():
    with pytest.raises(ConfigError) as error:
        load_config({"scenario": "x" * 1_000_000, "n_humans": list(range(100_000))})
    assert "scenario" in str(error.value) and "n_humans" in str(error.value) and len(str(error.value)) < 3000


# ---- the pieces every socnav config shares (one base, one reader, one merge, one error formatter) ----

def test_every_config_model_uses_the_one_strict_base():
    from socnav.config import StrictModel
    from socnav.experiments.spec import Budget, Evaluation, Experiment, Grid, Safety, Study
    from socnav.rl.presets import AlgoConfig
    from socnav.safety.rule import Thresholds

    for model in (EnvConfig, AlgoConfig, Thresholds, Experiment, Grid, Evaluation, Study, Safety, Budget):
        assert issubclass(model, StrictModel), model


def test_a_validated_config_passes_through_load_config_as_an_equal_copy():
    config = load_config({"scenario": "position_swap", "n_humans": [1, 3]})
    again = load_config(config)
    assert again == config and again is not config and again.reward is not config.reward
    assert load_config(config, n_humans=2).n_humans == 2  # overrides of a validated config are validated too


def test_deep_merge_merges_nested_mappings_without_touching_its_inputs():
    from socnav.config import deep_merge

    base = {"reward": {"goal": 1.0, "time": 0.5}, "scenario": "random"}
    merged = deep_merge(base, {"reward": {"goal": 2.0}, "n_humans": 3})
    assert merged == {"reward": {"goal": 2.0, "time": 0.5}, "scenario": "random", "n_humans": 3}
    assert base == {"reward": {"goal": 1.0, "time": 0.5}, "scenario": "random"}


def test_read_mapping_file_names_the_file_and_reads_json_only_when_asked(tmp_path):
    from socnav.config import read_mapping_file

    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing but a comment\n")
    assert read_mapping_file(empty, "config") == {}
    with pytest.raises(ConfigError, match=r"^preset file not found: .*missing\.yaml"):
        read_mapping_file(tmp_path / "missing.yaml", "preset")
    data = tmp_path / "t.json"
    data.write_text('{"lambda_ep": Infinity}')
    assert read_mapping_file(data, "thresholds", allow_json=True) == {"lambda_ep": float("inf")}
    with pytest.raises(ValueError, match=r"^thresholds file .*t\.json is not valid JSON"):
        data.write_text("{oops")
        read_mapping_file(data, "thresholds", ValueError, allow_json=True)


def test_the_one_formatter_names_path_problem_allowed_values_and_value():
    from pydantic import ValidationError

    from socnav.config import format_validation_error
    from socnav.experiments.spec import Experiment

    with pytest.raises(ValidationError) as error:
        Experiment.model_validate({"name": "x", "grid": {"algorithms": ["ppo"], "train_scenarios": ["random"],
                                                         "seeds": 1},
                                   "evaluation": {"scenarios": ["random"], "initial_heading": 1},
                                   "study": {"kk": 3}, "budgets": {"quick": {"seedz": 2}}})
    lines = format_validation_error(error.value, "invalid experiment (x.yaml):", Experiment).splitlines()
    assert lines[0] == "invalid experiment (x.yaml):"
    assert "  - grid.timesteps: required field is missing (required here: algorithms, train_scenarios, seeds, " \
           "timesteps)" in lines
    assert any(line.startswith("  - evaluation.initial_heading: unknown field; allowed fields: scenarios, episodes")
               for line in lines)
    assert any(line.startswith("  - study.kk: unknown field; allowed fields: estimators, perturbations, k")
               and line.endswith("did you mean k? (got 3)") for line in lines)  # through Optional[Study]
    # through dict[str, Budget]
    assert "  - budgets.quick.seedz: unknown field; did you mean seeds or mc_seed? (got 2)" in lines
    assert not any("Value error" in line for line in lines)
