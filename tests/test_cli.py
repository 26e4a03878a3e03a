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
    assert len(list(tmp_path.glob("*.csv"))) == 9
    assert "odv-ppo-drop (pretrained)" in result.output
