"""The `socnav` command line, driven through typer's runner: results, files and clear errors."""

import json

import pandas as pd
import pytest
from typer.testing import CliRunner

from socnav.cli import app
from socnav.experiments.spec import MAX_EPISODES

runner = CliRunner()


def test_evaluate_prints_metrics_and_writes_records(tmp_path):
    out = tmp_path / "records.parquet"
    result = runner.invoke(app, ["evaluate", "--controller", "orca", "--scenario", "position_swap", "--episodes", "6",
                                 "--seed", "3", "--out", str(out)])
    assert result.exit_code == 0, result.output
    for header in ("Goal %", "Col. %", "TO %", "PV", "Return"):
        assert header in result.output
    records = pd.read_parquet(out)
    assert list(records["seed"]) == [3, 4, 5, 6, 7, 8]
    assert set(records["outcome"]) <= {"goal", "collision", "timeout"}


def test_evaluate_rejects_bad_input_clearly(tmp_path):
    result = runner.invoke(app, ["evaluate", "--controller", "teleport"])
    assert result.exit_code == 2 and "--controller 'teleport'" in result.output
    assert "allowed: orca, straight" in result.output
    result = runner.invoke(app, ["evaluate", "--scenario", "maze", "--episodes", "1"])
    assert result.exit_code == 2 and "scenario" in result.output and "allowed" in result.output
    result = runner.invoke(app, ["evaluate", "--episodes", "1", "--out", str(tmp_path / "x.txt")])
    assert result.exit_code == 2 and ".csv" in result.output
    assert "Traceback" not in result.output


def test_demo_writes_tables_and_animation(tmp_path):
    result = runner.invoke(app, ["demo", "--episodes", "2", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "orca_circle_crossing.gif").stat().st_size > 10_000
    assert (tmp_path / "orca_doorway.gif").stat().st_size > 10_000  # the global planner's path drawn
    assert (tmp_path / "odv_ppo_drop_position_swap.gif").stat().st_size > 10_000
    assert (tmp_path / "pretrained-maps_doorway.gif").stat().st_size > 10_000  # the map policy inside its layer
    from socnav.sim.scenarios import scenario_names

    baselines = 2 * len(scenario_names(self_contained=True))  # straight and ORCA in every scenario (maps included)
    # the map policy alone and in its layer; the policy, and it perturbed without the layer, with the paper's rule
    # and with the two comparison layers
    assert len(list(tmp_path.glob("*.csv"))) == baselines + 2 + 5
    maps_alone = pd.read_csv(tmp_path / "pretrained-maps_doorway.csv")
    maps_layer = pd.read_csv(tmp_path / "pretrained-maps_doorway_safety.csv")
    assert list(maps_alone["seed"]) == list(maps_layer["seed"]) and "fallback_steps" in maps_layer
    assert "pretrained-maps / doorway + safety layer" in result.output
    assert "odv-ppo-drop (pretrained)" in result.output
    # The safety layer's part: the same perturbed episodes without and with each layer.
    plain = pd.read_csv(tmp_path / "perturbed_position_swap.csv")
    words = " ".join(result.output.split())
    for name in ("safety", "proximity_only", "time_to_collision"):
        layer = pd.read_csv(tmp_path / f"perturbed_position_swap_{name}.csv")
        assert list(plain["seed"]) == list(layer["seed"])
        prevented = int((plain["outcome"] == "collision").sum() - (layer["outcome"] == "collision").sum())
        assert f"{prevented} prevented" in words
        assert "fallback_steps" in layer
    assert "time to collision (calibrated for the shipped policy" in words
    assert "fallback drove" in result.output


def test_calibrate_writes_a_threshold_file_that_animate_uses(tmp_path):
    out = tmp_path / "mc.yaml"
    # the PPO policy: it collides in two calibration episodes, where the shipped one does not (nothing to calibrate)
    result = runner.invoke(app, ["calibrate", "--model", "pretrained-ppo", "--episodes", "2", "--k", "4",
                                 "--false-activation-budget", "0.1", "--out", str(out)])
    assert result.exit_code == 0, result.output
    from socnav.safety import load_thresholds

    thresholds = load_thresholds(out)
    report = json.loads(out.with_suffix(".report.json").read_text())
    assert report["false_activation_budget"] == 0.1
    assert report["proximity_searched"] == ["abs-relative-speed", "closing-speed"]
    # The calibration episodes hold collisions, so candidates were replayed and exactly one was chosen: the file's.
    assert report["n_collisions"] > 0 and report["candidates"], "nothing to calibrate on: the test would be vacuous"
    assert all(c["plain_collisions"] == report["n_collisions"] for c in report["candidates"])
    assert {c["proximity"] for c in report["candidates"]} <= set(report["proximity_searched"])
    (chosen,) = [c for c in report["candidates"] if c["chosen"]]
    fields = thresholds.model_dump()
    assert {name: chosen[name] for name in fields} == fields == report["thresholds"]
    assert thresholds != type(thresholds).never()
    assert chosen["false_activation_upper"] <= report["false_activation_budget"]
    for name in ("prevented_fraction", "prevented_worst", "false_activation_rate", "false_activation_upper"):
        assert report[name] == chosen[name]
    # No candidate within the budget prevents more collisions (worst perturbation type first, then the mean).
    feasible = [c for c in report["candidates"] if c["false_activation_upper"] <= report["false_activation_budget"]]
    best = max((c["prevented_worst"], c["prevented_fraction"]) for c in feasible)
    assert (chosen["prevented_worst"], chosen["prevented_fraction"]) == best
    gif = tmp_path / "episode.gif"
    result = runner.invoke(app, ["animate", "--model", "pretrained-ppo", "--k", "4", "--perturb",
                                 "observation_noise=0.5", "--safety", str(out), "--out", str(gif)])
    assert result.exit_code == 0, result.output
    assert gif.stat().st_size > 10_000 and "fallback on" in result.output


def test_uncertainty_commands_reject_bad_input_clearly(tmp_path):
    def run(*args):
        result = runner.invoke(app, list(args))
        return result.exit_code, " ".join(result.output.split())  # rich wraps long lines

    code, output = run("calibrate", "--model", "pretrained", "--proximity", "telepathy")
    assert code == 2 and "allowed: both, abs-relative-speed, closing-speed" in output
    code, output = run("animate", "--estimator", "ensemble", "--members", str(tmp_path / "*.zip"))
    assert code == 2 and "at least 2" in output
    code, output = run("animate", "--model", "pretrained", "--perturb", "wind=3")
    assert code == 2 and "wind" in output and "Traceback" not in output


def test_deprecated_option_names_are_hidden_aliases_that_warn(tmp_path):
    """`evaluate --policy` is the deprecated name of `--controller` (`--model` takes trained policies), `calibrate
    --budget` that of `--false-activation-budget` (`socnav run --budget` names an experiment's compute budget)."""
    out = tmp_path / "records.csv"
    result = runner.invoke(app, ["evaluate", "--policy", "straight", "--scenario", "position_swap", "--episodes", "2",
                                 "--out", str(out)])
    assert result.exit_code == 0 and "--policy is deprecated: use --controller" in result.output, result.output
    assert "straight" in result.output and len(pd.read_csv(out)) == 2
    result = runner.invoke(app, ["calibrate", "--budget", "0.1", "--out", str(tmp_path / "bad.txt")])
    assert "--budget is deprecated: use --false-activation-budget" in result.output
    assert result.exit_code == 2 and "--out must be a .yaml or .json" in result.output  # then the usual checks
    for command, old in (("evaluate", "--policy"), ("calibrate", "--budget")):
        assert old not in runner.invoke(app, [command, "--help"]).output


def test_evaluate_in_a_world_with_walls_reports_wall_collisions_apart(tmp_path):
    out = tmp_path / "straight.csv"
    result = runner.invoke(app, ["evaluate", "--controller", "straight", "--config", str(_pillar_config(tmp_path)),
                                 "--episodes", "8", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "Wall %" in result.output
    records = pd.read_csv(out)
    # straight drives into the pillar on its path: those episodes end as wall collisions, not human collisions
    assert (records["outcome"] == "collision_wall").sum() >= 6
    assert records.loc[records["outcome"] == "collision_wall", "collision_obstacle"].all()


def _pillar_config(tmp_path):
    path = tmp_path / "pillar.yaml"
    path.write_text("scenario: circle_crossing\nn_humans: 0\n"
                    "obstacles: [[[0.2, 0.2], [1.0, 0.2], [1.0, 1.0], [0.2, 1.0]]]\n")
    return path


@pytest.mark.parametrize("command", ["evaluate", "calibrate", "demo"])
def test_episode_counts_out_of_range_are_refused_alike_by_every_command(command, tmp_path):
    bounds = {"0": "greater than or equal to 1", str(MAX_EPISODES + 1): f"less than or equal to {MAX_EPISODES}"}
    for bad, bound in bounds.items():
        result = runner.invoke(app, [command, "--episodes", bad, "--out", str(tmp_path / "never")])
        output = " ".join(result.output.split())
        assert result.exit_code == 2 and f"Invalid value for '--episodes': Input should be {bound}" in output, output
    assert not (tmp_path / "never").exists()


def test_options_shared_by_commands_are_declared_alike():
    import typer.main

    commands = typer.main.get_command(app).commands

    def declared(command, name):
        (param,) = [param for param in commands[command].params if param.name == name]
        return tuple(param.opts), param.help, getattr(param, "min", None), getattr(param, "max", None)

    for name, users in (("config", ("train", "evaluate", "animate", "calibrate", "tune")),
                        ("members", ("evaluate", "animate", "calibrate")), ("perturb", ("evaluate", "animate")),
                        ("sensing", ("evaluate", "animate")), ("eval_episodes", ("train", "tune")),
                        ("n_humans", ("train", "evaluate", "tune")), ("k", ("animate", "calibrate"))):
        assert len({declared(command, name) for command in users}) == 1, name
