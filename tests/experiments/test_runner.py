"""The experiment runner: a tiny experiment end to end on the local process pool and on Ray, a sweep killed with
SIGKILL and run again finishes with every unit's results exactly once, corrupt or half-written units are redone,
failing units are reported without stopping the others; and `socnav tune` writes a usable preset."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml
from _extras import require
from typer.testing import CliRunner

from socnav.cli import app
from socnav.experiments.registry import EXECUTORS, PLANNERS, ExecutorResult, unit_dir
from socnav.experiments.report import build_report
from socnav.experiments.runner import Reporter, RunnerError, read_plan, run_experiment, unit_lock_path, unit_states
from socnav.experiments.spec import Unit, load_experiment, plan_units
from socnav.io import file_lock, read_table

SMOKE = Path(__file__).resolve().parents[2] / "configs" / "experiments" / "smoke.yaml"
runner = CliRunner()


def _check_complete(root: Path, experiment) -> dict[str, dict]:
    """Every unit done, each evaluation's records exactly once; returns the done markers by unit id."""
    units = plan_units(experiment)
    states = unit_states(root, units)
    assert set(states.values()) == {"done"}, states
    markers = {}
    for unit in units:
        markers[unit.id] = json.loads((unit_dir(root, unit) / "done.json").read_text())
        if unit.kind == "eval":
            records = read_table(unit_dir(root, unit) / "episodes.parquet")
            assert records["episode"].tolist() == list(range(experiment.evaluation.episodes))
            assert set(records["eval_scenario"]) == {unit.params["eval_scenario"]}
        else:
            curve = read_table(unit_dir(root, unit) / "curve.csv")
            assert curve["timesteps"].is_monotonic_increasing and curve["timesteps"].is_unique
            assert curve["timesteps"].iloc[-1] == experiment.grid.timesteps
            validation = read_table(unit_dir(root, unit) / "eval.csv")
            assert validation["timesteps"].is_unique
    table = pd.read_csv(build_report(root) .parent / "table1.csv")
    grid = experiment.grid
    n_evals = len(grid.algorithms) * len(grid.train_scenarios) * len(experiment.evaluation.scenarios)
    assert len(table) == n_evals
    assert (table["episodes"] == experiment.evaluation.episodes * len(experiment.grid.seeds)).all()
    return markers


@pytest.fixture(scope="module")
def local_run(tmp_path_factory) -> Path:
    """The smoke experiment (quick budget) run once on a 2-process pool."""
    root = tmp_path_factory.mktemp("local") / "run"
    summary = run_experiment(load_experiment(SMOKE, "quick"), root, backend="local", workers=2, source=SMOKE,
                             reporter=_RecordingReporter())
    assert summary.ok and summary.count("done") == 6, summary.outcomes
    return root


#: unit id -> the (done, total, what) progress reports the local_run sweep received for it
PROGRESS_REPORTS: dict[str, list[tuple[int, int, str]]] = {}


class _RecordingReporter(Reporter):
    def unit_progress(self, unit, done, total, what):
        PROGRESS_REPORTS.setdefault(unit.id, []).append((done, total, what))


def test_running_units_report_their_progress_from_the_worker(local_run):
    experiment = load_experiment(SMOKE, "quick")
    trains = [unit for unit in plan_units(experiment) if unit.kind == "train"]
    reported = [unit for unit in trains if unit.id in PROGRESS_REPORTS]
    assert reported, PROGRESS_REPORTS  # a training of thousands of steps is polled at least once
    for unit in reported:
        reports = PROGRESS_REPORTS[unit.id]
        assert {(total, what) for _, total, what in reports} == {(experiment.grid.timesteps, "steps")}
        done = [d for d, _, _ in reports]
        assert done == sorted(done) and 0 <= done[0] <= done[-1] <= experiment.grid.timesteps
    for unit in plan_units(experiment):  # a finished unit leaves no progress file behind
        assert not (unit_dir(local_run, unit) / "progress.json").exists()


def test_local_backend_end_to_end(local_run):
    experiment = load_experiment(SMOKE, "quick")
    _check_complete(local_run, experiment)
    assert (local_run / "experiment.yaml").read_text() == SMOKE.read_text()
    resolved, units = read_plan(local_run)
    assert resolved["budget"] == "quick" and [u.id for u in units] == [u.id for u in plan_units(experiment)]
    again = run_experiment(experiment, local_run, workers=2)  # nothing left to do
    assert again.count("skipped") == 6 and again.ok


def test_ray_backend_end_to_end(tmp_path):
    ray = require("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        experiment = load_experiment(SMOKE, "quick")
        summary = run_experiment(experiment, tmp_path / "run", backend="ray")
        assert summary.ok and summary.count("done") == 6, summary.outcomes
        _check_complete(tmp_path / "run", experiment)
    finally:
        ray.shutdown()


def test_ray_missing_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(RunnerError, match=r'pip install (-e "\.|"socnav)\[ray\]"'):  # checkout or installed
        run_experiment(load_experiment(SMOKE, "quick"), tmp_path / "run", backend="ray")


def _wait_for(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


@pytest.mark.heavy
def test_killed_sweep_resumes_with_each_result_exactly_once(tmp_path):
    experiment = load_experiment(SMOKE)  # grid as written: 4,096 steps with a checkpoint at 2,048
    root = tmp_path / "run"
    second = root / "train" / "circle_crossing" / "odv-ppo-drop" / "seed0"
    process = subprocess.Popen(
        [sys.executable, "-m", "socnav.cli", "run", str(SMOKE), "--out", str(root), "--workers", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
    )
    try:
        # Kill when the first training is finished and the second has checkpointed half-way.
        _wait_for(lambda: (second / "checkpoints" / "state.json").exists() or process.poll() is not None, 120,
                  "the second training's checkpoint")
        assert process.poll() is None, process.stderr.read().decode() if process.stderr else ""
        os.kill(process.pid, signal.SIGKILL)  # the runner only: its worker must notice and stop by itself
        process.wait(10)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    unit = next(u for u in plan_units(experiment) if u.id == "train/circle_crossing/odv-ppo-drop/seed0")

    def worker_gone() -> bool:
        with file_lock(unit_lock_path(root.resolve(), unit), blocking=False) as free:
            return free

    _wait_for(worker_gone, 10, "the orphaned worker to exit")
    states = unit_states(root, plan_units(experiment))
    assert states["train/circle_crossing/ppo/seed0"] == "done"
    assert states[unit.id] == "partial" and not (second / "done.json").exists()

    summary = run_experiment(experiment, root, workers=0)
    assert summary.ok, summary.outcomes
    assert summary.outcomes["train/circle_crossing/ppo/seed0"].status == "skipped"
    assert summary.outcomes[unit.id].status == "done"
    markers = _check_complete(root, experiment)
    assert markers[unit.id]["resumed"] is True
    validations = read_table(second / "eval.csv")
    assert validations["timesteps"].tolist() == [2048, 4096]


def test_corrupt_and_half_written_units_are_redone(local_run, tmp_path):
    root = tmp_path / "run"
    shutil.copytree(local_run, root)
    experiment = load_experiment(SMOKE, "quick")
    units = {u.id: u for u in plan_units(experiment)}
    before = {uid: json.loads((unit_dir(root, uid) / "done.json").read_text()) for uid in units}

    # 1. an evaluation whose records were truncated after it finished
    truncated = "eval/circle_crossing/ppo/seed0/random"
    path = unit_dir(root, truncated) / "episodes.parquet"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    # 2. a training whose completion marker is half-written
    torn = "train/circle_crossing/odv-ppo-drop/seed0"
    marker = unit_dir(root, torn) / "done.json"
    marker.write_text(marker.read_text()[:40])
    # 3. an evaluation killed half-way: files but no marker
    half = "eval/circle_crossing/ppo/seed0/circle_crossing"
    (unit_dir(root, half) / "done.json").unlink()
    (unit_dir(root, half) / "summary.json").write_text("{")

    states = unit_states(root, list(units.values()))
    assert states[truncated] == "corrupt" and states[torn] == "corrupt" and states[half] == "partial"
    # the torn training's evaluations are no longer done either (their input is not a finished model)
    assert states["eval/circle_crossing/odv-ppo-drop/seed0/random"] == "stale"

    summary = run_experiment(experiment, root, workers=0)
    redone = {uid for uid, outcome in summary.outcomes.items() if outcome.status == "done"}
    # The torn training, redone from scratch with the same seed, writes a byte-identical model.zip (policy files
    # have fixed timestamps), so the evaluations of that model stay valid and are not redone.
    assert (unit_dir(root, torn) / "model.zip").read_bytes() == (unit_dir(local_run, torn) / "model.zip").read_bytes()
    assert redone == {truncated, torn, half}
    assert summary.outcomes["train/circle_crossing/ppo/seed0"].status == "skipped"
    markers = _check_complete(root, experiment)
    assert markers[torn]["resumed"] is False  # a corrupt unit is wiped and redone from scratch
    assert markers["train/circle_crossing/ppo/seed0"] == before["train/circle_crossing/ppo/seed0"]


@pytest.mark.heavy
def test_partial_training_resumes_only_from_a_consistent_checkpoint(local_run, tmp_path):
    from socnav.experiments.runner import prepare_unit_dir

    root = tmp_path / "run"
    shutil.copytree(local_run, root)
    unit = next(u for u in plan_units(load_experiment(SMOKE, "quick")) if u.id == "train/circle_crossing/ppo/seed0")
    directory = unit_dir(root, unit)
    (directory / "done.json").unlink()  # killed after its last checkpoint, before its marker
    prepare_unit_dir(root, unit, "partial")
    state_file = directory / "checkpoints" / "state.json"
    state = json.loads(state_file.read_text())
    assert (directory / "checkpoints" / state["checkpoint"]).is_file()  # kept: train(resume=True) continues from it

    state_file.write_text(json.dumps({**state, "num_timesteps": state["num_timesteps"] - 256}))
    prepare_unit_dir(root, unit, "partial")  # killed between the model and its state: start afresh
    assert not (directory / "checkpoints").exists() and (directory / "unit.json").is_file()

    summary = run_experiment(load_experiment(SMOKE, "quick"), root, workers=0)
    assert summary.outcomes[unit.id].status == "done"
    assert json.loads((directory / "done.json").read_text())["resumed"] is False


def test_failing_unit_is_reported_and_the_others_go_on(tmp_path, monkeypatch):
    calls: list[str] = []

    def plan(experiment) -> list[Unit]:
        return [Unit("demo/boom", "boom", {"n": 1}), Unit("demo/fine", "fine", {"n": 2}),
                Unit("demo/after-boom", "fine", {"n": 3}, deps=("demo/boom",))]

    def boom(root, unit, directory) -> ExecutorResult:
        calls.append(unit.id)
        raise ValueError("boom: this unit cannot work")

    def fine(root, unit, directory) -> ExecutorResult:
        calls.append(unit.id)
        (directory / "out.txt").write_text("ok")
        return ExecutorResult(["out.txt"])

    monkeypatch.setitem(PLANNERS, "failing-demo", plan)
    monkeypatch.setitem(EXECUTORS, "boom", boom)
    monkeypatch.setitem(EXECUTORS, "fine", fine)
    spec = yaml.safe_load(SMOKE.read_text())
    spec.update(kind="failing-demo", budgets={})
    path = tmp_path / "failing.yaml"
    path.write_text(yaml.safe_dump(spec))
    out = tmp_path / "run"

    result = runner.invoke(app, ["run", str(path), "--out", str(out), "--workers", "0"])
    assert result.exit_code == 1, result.output
    assert "demo/boom" in result.output and "boom: this unit cannot work" in result.output
    assert "dependency demo/boom failed" in result.output
    assert "boom: this unit cannot work" in (out / "demo" / "boom" / "error.txt").read_text()
    assert calls == ["demo/boom", "demo/fine"]
    assert (out / "demo" / "fine" / "done.json").is_file()

    monkeypatch.setitem(EXECUTORS, "boom", fine)  # fixed: the rerun redoes the failed unit and its dependant
    calls.clear()
    result = runner.invoke(app, ["run", str(path), "--out", str(out), "--workers", "0"])
    assert result.exit_code == 0, result.output
    assert calls == ["demo/boom", "demo/after-boom"]
    assert not (out / "demo" / "boom" / "error.txt").exists()


def test_busy_or_foreign_run_directory_is_refused(tmp_path):
    experiment = load_experiment(SMOKE, "quick")
    root = tmp_path / "run"
    root.mkdir()
    with file_lock(root / ".lock"), pytest.raises(RunnerError, match="another socnav run is working"):
        run_experiment(experiment, root, workers=0)
    (root / "resolved.json").write_text(json.dumps({"experiment": {"name": "smoke", "budget": None}}))
    with pytest.raises(RunnerError, match="holds experiment 'smoke' with budget None"):
        run_experiment(experiment, root, workers=0)


def test_tune_runs_trials_and_writes_a_preset(tmp_path):
    optuna = require("optuna")
    storage = f"sqlite:///{tmp_path / 'tune.db'}"
    preset = tmp_path / "preset.yaml"
    result = runner.invoke(app, [
        "tune", "--algo", "ppo", "--scenario", "position_swap", "--trials", "2", "--timesteps", "768",
        "--n-envs", "1", "--eval-every", "256", "--eval-episodes", "2", "--storage", storage,
        "--out", str(tmp_path / "trials"), "--write-preset", str(preset),
    ])
    assert result.exit_code == 0, result.output
    study = optuna.load_study(study_name="ppo_position_swap", storage=storage)
    assert len(study.trials) == 2
    assert all(trial.intermediate_values for trial in study.trials)  # periodic validations reported
    values = yaml.safe_load(preset.read_text())
    assert set(values) == {"learning_rate", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda",
                           "clip_range", "ent_coef"}
    from socnav.rl.presets import resolve_config

    resolve_config("ppo", values)  # the preset is valid input for train / experiment files
    assert "best of study" in result.output


def test_a_progress_file_is_throttled_and_an_unsound_one_reads_as_none(tmp_path):
    from socnav.experiments.registry import UnitProgress, read_progress

    bar = UnitProgress(tmp_path, 10, "episodes", every=3600.0)
    bar.advance(3)
    assert read_progress(tmp_path) == (3, 10, "episodes")
    bar.advance(2)  # within the interval: not written
    assert read_progress(tmp_path) == (3, 10, "episodes")
    bar.advance(5)  # complete: always written
    assert read_progress(tmp_path) == (10, 10, "episodes")
    for text in ["{", '{"done": 11, "total": 10, "unit": "x"}', '{"done": -1, "total": 10, "unit": "x"}',
                 '{"done": 1, "total": 0, "unit": "x"}', "[1, 2]", "[" * 100_000]:
        (tmp_path / "progress.json").write_text(text)
        assert read_progress(tmp_path) is None, text
    (tmp_path / "progress.json").unlink()
    (tmp_path / "progress.json").symlink_to(tmp_path / "elsewhere.json")
    (tmp_path / "elsewhere.json").write_text('{"done": 1, "total": 2, "unit": "x"}')
    assert read_progress(tmp_path) is None  # never read through a link
