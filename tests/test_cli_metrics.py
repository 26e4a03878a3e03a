"""`socnav evaluate --metrics`: the default prints the paper's table and records the world's episode columns only;
other choices print and record every metric of the registry; unknown names are a clear error with the allowed names
and the closest one."""

import pandas as pd
from typer.testing import CliRunner

from socnav.cli import app
from socnav.envs.rollout import EPISODE_COLUMNS
from socnav.sim.metrics import ALL_METRICS, METRIC_RECORD_COLUMNS

runner = CliRunner()
COMMON = ["evaluate", "--controller", "orca", "--scenario", "position_swap", "--episodes", "4", "--seed", "2"]


def test_default_metrics_record_the_episode_columns_only(tmp_path):
    default, explicit = tmp_path / "default.csv", tmp_path / "explicit.csv"
    result = runner.invoke(app, [*COMMON, "--out", str(default)])
    assert result.exit_code == 0, result.output
    assert runner.invoke(app, [*COMMON, "--metrics", "default", "--out", str(explicit)]).exit_code == 0
    records = pd.read_csv(default)
    assert list(records.columns) == list(EPISODE_COLUMNS)
    pd.testing.assert_frame_equal(records, pd.read_csv(explicit))
    for header in ("Goal %", "Col. %", "TO %", "PV/200 ep.", "nav time (s)", "Return"):
        assert header in result.output
    assert "spl" not in result.output


def test_all_metrics_are_printed_and_recorded_after_unchanged_episode_columns(tmp_path):
    default, extended = tmp_path / "default.csv", tmp_path / "all.parquet"
    assert runner.invoke(app, [*COMMON, "--out", str(default)]).exit_code == 0
    result = runner.invoke(app, [*COMMON, "--metrics", "all", "--out", str(extended)], terminal_width=200)
    assert result.exit_code == 0, result.output
    for name in ALL_METRICS:
        assert name in result.output
    records = pd.read_parquet(extended)
    assert list(records.columns) == [*EPISODE_COLUMNS, *METRIC_RECORD_COLUMNS]
    pd.testing.assert_frame_equal(records[list(EPISODE_COLUMNS)], pd.read_csv(default), check_dtype=False)


def test_named_metrics_and_bad_names(tmp_path):
    result = runner.invoke(app, [*COMMON, "--metrics", "spl,jerk_max", "--out", str(tmp_path / "r.csv")])
    assert result.exit_code == 0, result.output
    assert "spl" in result.output and "jerk_max" in result.output and "goal_pct" not in result.output
    result = runner.invoke(app, [*COMMON, "--metrics", "spl,jerk_mx"])
    assert result.exit_code == 2 and "--metrics" in result.output and "'jerk_mx'" in result.output
    assert "did you mean 'jerk_max'" in result.output and "allowed: default, all" in result.output
    assert "Traceback" not in result.output
