import json
"""The `socnav` command line, driven through typer's runner: results, files and clear errors."""

import pandas as pd
from typer.testing import CliRunner

from socnav.cli import app

runner = CliRunner()


def test_evaluate_prints_metrics_and_writes_records(tmp_path):
    out = tmp_path / "records.parquet"
    result = runner.invoke(app, ["evaluate", "--policy", "orca", "--scenario", "position_swap", "--episodes", "6",
                                 "--seed", "3", "--out", str(out)])
    assert result.exit_code == 0, result.output
    for header in ("Goal %", "Col. %", "TO %", "PV", "Return"):
        assert header in result.output
    records = pd.read_parquet(out)
    assert list(records["seed"]) == [3, 4, 5, 6, 7, 8]
    assert set(records["outcome"]) <= {"goal", "collision", "timeout"}


def test_evaluate_rejects_bad_input_clearly(tmp_path):
    result = runner.invoke(app, ["evaluate", "--policy", "teleport"])
    assert result.exit_code == 2 and "allowed: orca, straight" in result.output
    result = runner.invoke(app, ["evaluate", "--scenario", "maze", "--episodes", "1"])
    assert result.exit_code == 2 and "scenario" in result.output and "allowed" in result.output
    result = runner.invoke(app, ["evaluate", "--episodes", "1", "--out", str(tmp_path / "x.txt")])
    assert result.exit_code == 2 and ".csv" in result.output
    assert "Traceback" not in result.output


def test_demo_writes_tables_and_animation(tmp_path):
    result = runner.invoke(app, ["demo", "--episodes", "2", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "orca_circle_crossing.gif").stat().st_size > 10_000
    assert (tmp_path / "odv_ppo_drop_position_swap.gif").stat().st_size > 10_000
    assert len(list(tmp_path.glob("*.csv"))) == 11  # 8 baseline runs, the policy, and it perturbed without/with safety
    assert "odv-ppo-drop (pretrained)" in result.output
    # The safety layer's part: the same perturbed episodes without and with it.
    plain, safe = (pd.read_csv(p) for p in sorted(tmp_path.glob("perturbed_*.csv")))
    assert list(plain["seed"]) == list(safe["seed"])
    prevented = int((plain["outcome"] == "collision").sum() - (safe["outcome"] == "collision").sum())
    assert f"{prevented} prevented" in " ".join(result.output.split())
    assert "fallback drove" in result.output


def test_calibrate_writes_a_threshold_file_that_animate_uses(tmp_path):
    out = tmp_path / "mc.yaml"
    result = runner.invoke(app, ["calibrate", "--model", "pretrained", "--episodes", "2", "--k", "4",
                                 "--out", str(out)])
    assert result.exit_code == 0, result.output
    from socnav.safety import load_thresholds

    thresholds = load_thresholds(out)
    report = json.loads(out.with_suffix(".report.json").read_text())
    assert report["proximity_searched"] == ["abs-relative-speed", "closing-speed"]
    if report["n_collisions"]:  # candidates replayed; the chosen one is the file's
        chosen = [c for c in report["candidates"] if c["chosen"]]
        assert not chosen or chosen[0]["proximity"] == thresholds.proximity
    gif = tmp_path / "episode.gif"
    result = runner.invoke(app, ["animate", "--model", "pretrained", "--k", "4", "--perturb", "observation_noise=0.5",
                                 "--safety", str(out), "--out", str(gif)])
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
