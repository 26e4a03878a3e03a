"""Safety nets a new user still missed: outputs never replaced or mistyped directories created unless told, every
option checked before a model loads, an exported navigator evaluated like the policy it came from, Ctrl-C keeping
the work done, --humans, a dry run refusing what the run refuses, a note for a policy outside its training world,
progress from the Python rollout API, and `socnav plot`."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pandas as pd
import pytest
from _extras import require
from typer.testing import CliRunner

from socnav.cli import app

REPO = Path(__file__).resolve().parents[1]
runner = CliRunner()


def run(*args: object) -> tuple[int, str]:
    """Exit code and output (rich's wrapping undone) of `socnav ARGS`; an escaped exception fails the test."""
    result = runner.invoke(app, [str(a) for a in args])
    assert "Traceback" not in result.output, result.output
    if result.exit_code not in (0, 2, 130):
        raise AssertionError(f"exit {result.exit_code}: {result.exception!r}\n{result.output}")
    return result.exit_code, " ".join(result.output.split())


class WorkStarted(Exception):
    """Raised by a patched step: the command went on to work it should have refused first."""


def _no_work(*args, **kwargs):
    raise WorkStarted("the command started its work")


@pytest.fixture
def no_work(monkeypatch):
    """Every command's expensive step (loading a model included) raises WorkStarted."""
    # Imported first: a module importing rollout_episodes by name while it is patched would keep the patch.
    import socnav.cli.workflows.demo
    import socnav.rl.training  # noqa: F401

    for target in ("socnav.envs.rollout.rollout_episodes", "socnav.safety.calibrate_thresholds",
                   "socnav.cli.workflows.animation.animate_episode", "socnav.rl.convert.to_sb3",
                   "socnav.rl.persistence.load_policy", "socnav.rl.training.train"):
        monkeypatch.setattr(target, _no_work)


def _curve_run(tmp_path: Path) -> Path:
    """A training run directory as far as `socnav plot` reads it: a curve.csv of three rollouts."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    pd.DataFrame({"timesteps": [256, 512, 768], "wall_time_s": [1.0, 2.0, 3.0], "ep_rew_mean": [-1.0, 0.0, 0.5],
                  "ep_len_mean": [40.0, 35.0, 30.0], "success_rate": [0.2, 0.5, 0.7]}).to_csv(run_dir / "curve.csv",
                                                                                            index=False)
    return run_dir


# ------------------------------------------------------------------------------------------ outputs

def test_evaluate_out_refuses_an_existing_file_unless_force(tmp_path):
    out = tmp_path / "r.csv"
    args = ["evaluate", "--controller", "straight", "--scenario", "position_swap", "--episodes", "2", "--out", out]
    assert run(*args)[0] == 0
    out.write_text("the first results")
    code, output = run(*args)
    assert code == 2 and f"--out {out} exists; pass --force" in output
    assert out.read_text() == "the first results"
    code, output = run(*args, "--force")
    assert code == 0, output
    assert len(pd.read_csv(out)) == 2


@pytest.mark.parametrize("command, existing", [
    (["export", "pretrained", "--out", "{path}"], "navigator.onnx"),
    (["calibrate", "--model", "pretrained", "--out", "{path}"], "thresholds.yaml"),
    (["calibrate", "--model", "pretrained", "--out", "{dir}/thresholds.yaml"], "thresholds.report.json"),
    (["animate", "--model", "pretrained", "--out", "{path}"], "episode.gif"),
    (["convert", "pretrained", "--to-sb3", "{path}"], "sb3.zip"),
    (["plot", "{run}", "--out", "{path}"], "curve.png"),
    (["evaluate", "--model", "pretrained", "--out", "{path}"], "records.parquet"),
])
def test_no_output_is_replaced_unless_told(no_work, tmp_path, command, existing):
    path = tmp_path / existing
    path.write_text("kept")
    run_dir = _curve_run(tmp_path)
    code, output = run(*(part.format(path=path, dir=tmp_path, run=run_dir) for part in command))
    assert code == 2 and "exists; pass --force to replace it" in output, output
    assert path.read_text() == "kept"


def test_a_mistyped_output_directory_is_refused_not_created(no_work, monkeypatch, tmp_path):
    monkeypatch.setattr("socnav.export.export_onnx", _no_work)
    missing = tmp_path / "nonexistent" / "dir"
    code, output = run("export", "pretrained", "--out", missing / "x.onnx")
    assert code == 2 and f"directory {missing} does not exist" in output
    assert not missing.parent.exists()
    code, output = run("evaluate", "--episodes", "1", "--out", missing / "r.csv")
    assert code == 2 and "does not exist" in output and not missing.parent.exists()


def test_default_outputs_still_create_their_own_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, output = run("evaluate", "--controller", "straight", "--scenario", "position_swap", "--episodes", "1")
    assert code == 0, output
    assert len(list((tmp_path / "runs" / "evaluate").glob("*.csv"))) == 1
    code, output = run("evaluate", "--controller", "straight", "--scenario", "position_swap", "--episodes", "1")
    assert code == 2 and "exists; pass --force" in output  # the same evaluation again: its records are kept


def test_write_paths_refuse_what_is_not_a_new_or_regular_file(no_work, monkeypatch, tmp_path):
    monkeypatch.setattr("socnav.export.export_onnx", _no_work)
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    directory = tmp_path / "d.csv"
    directory.mkdir()
    cases = [
        (["evaluate", "--episodes", "1", "--out", fifo], "not a regular file"),
        (["evaluate", "--episodes", "1", "--out", directory], "is a directory"),
        (["evaluate", "--episodes", "1", "--out", "/proc/self/r.csv"], "system path"),
        (["export", "pretrained", "--out", "/dev/null", "--force"], "system path"),
        (["plot", _curve_run(tmp_path), "--out", "/proc/self/curve.png"], "system path"),
    ]
    for command, words in cases:
        code, output = run(*command)
        assert code == 2 and words in output, (command, output)
        assert output.count("error:") == 1


def test_report_keeps_an_earlier_report_unless_force(tmp_path):
    from socnav.experiments.runner import prepare_run_dir
    from socnav.experiments.spec import load_experiment

    smoke = REPO / "configs" / "experiments" / "smoke.yaml"
    root = tmp_path / "run"
    prepare_run_dir(root, load_experiment(smoke, "quick"), smoke)
    assert run("report", root)[0] == 0
    page = root / "report" / "report.md"
    page.write_text("edited")
    code, output = run("report", root)
    assert code == 2 and "report.md exists; pass --force" in output and page.read_text() == "edited"
    code, output = run("report", root, "--force")
    assert code == 0, output
    assert page.read_text() != "edited"


# ------------------------------------------------------------------------------------------ options first

@pytest.mark.parametrize("options, words", [
    (["evaluate", "--model", "pretrained", "--safety", "foo"], "--safety"),
    (["evaluate", "--model", "pretrained", "--safety", "mc", "--estimator", "bogus"], "allowed: mc, ensemble"),
    (["evaluate", "--model", "pretrained", "--safety", "mc", "--sensing", "psychic"], "--sensing 'psychic'"),
    (["evaluate", "--model", "pretrained", "--perturb", "wind=3"], "wind"),
    (["evaluate", "--model", "pretrained", "--humans", "socail_force"], "did you mean social_force"),
    (["evaluate", "--model", "pretrained", "--safety", "mc", "--k", "1000000"], "--k"),
    (["animate", "--model", "pretrained", "--estimator", "bogus"], "allowed: mc, ensemble"),
    (["animate", "--model", "pretrained", "--safety", "foo"], "--safety"),
    (["animate", "--model", "pretrained", "--perturb", "wind=3"], "wind"),
    (["calibrate", "--model", "pretrained", "--estimator", "ensemble"], "--members"),
    (["calibrate", "--model", "pretrained", "--humans", "orcaa"], "did you mean orca"),
    (["export", "pretrained", "--thresholds", "nosuch"], "--thresholds"),
])
def test_options_are_checked_before_a_model_loads(no_work, monkeypatch, options, words):
    monkeypatch.setattr("socnav.export.export_onnx", _no_work)
    code, output = run(*options)
    assert code == 2 and words in output, output


def test_k_is_bounded_as_the_export_bounds_it():
    require("onnxruntime")
    from socnav.cli.options import MAX_MC_SAMPLES
    from socnav.runtime.format import MAX_K

    assert MAX_MC_SAMPLES == MAX_K == 1000
    for command in (["evaluate"], ["animate"], ["calibrate"]):
        code, output = run(*command, "--k", MAX_K + 1)
        assert code == 2 and "'--k'" in output and str(MAX_K) in output, output


# ------------------------------------------------------------------------------------------ exported navigator

def test_evaluate_scores_an_exported_navigator_like_the_policy_it_came_from(tmp_path):
    require("onnx")
    require("onnxruntime")
    navigator = tmp_path / "navigator.onnx"
    assert run("export", "pretrained", "--out", navigator)[0] == 0
    episodes = ["--episodes", "6", "--seed", "11"]
    code, output = run("evaluate", "--model", navigator, *episodes, "--out", tmp_path / "onnx.csv")
    assert code == 0, output
    assert "corrupted" not in output and "the model's training world" in output
    code, output = run("evaluate", "--model", "pretrained", *episodes, "--out", tmp_path / "torch.csv")
    assert code == 0, output
    exported, torch_policy = pd.read_csv(tmp_path / "onnx.csv"), pd.read_csv(tmp_path / "torch.csv")
    assert list(exported["seed"]) == list(torch_policy["seed"]) == list(range(11, 17))
    assert list(exported["outcome"]) == list(torch_policy["outcome"])
    assert list(exported["length"]) == list(torch_policy["length"])
    code, output = run("evaluate", "--model", navigator, "--safety", "mc")
    assert code == 2 and "exported navigator" in output
    code, output = run("animate", "--model", navigator)
    assert code == 2 and "exported navigator" in output and "zip" not in output.split("exported navigator")[0]


# ------------------------------------------------------------------------------------------ Ctrl-C

TINY = ["--scenario", "position_swap", "--n-humans", "1", "--algo", "ppo", "--n-envs", "2", "--eval-episodes", "1",
        "--set", "n_steps=128"]


@pytest.fixture
def sigint_as_in_a_terminal():
    """Python's own SIGINT handler during the test, as in a terminal, put back after: a test run started as a
    background job of a non-interactive shell has SIGINT ignored, and then no Ctrl-C reaches a command at all."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_in_train_before_the_first_checkpoint_keeps_the_steps(monkeypatch, tmp_path, sigint_as_in_a_terminal):
    """Ctrl-C at step ~300 of a run whose first scheduled checkpoint is its end (1,024 steps): a checkpoint at the
    next rollout boundary (512 steps: rollouts of 2 x 128), and --resume continues from it."""
    from socnav.rl import training

    on_step = training._RunMonitor._on_step
    sent = []

    def ctrl_c_once(self):
        if self.model.num_timesteps >= 300 and not sent:
            sent.append(True)
            signal.raise_signal(signal.SIGINT)
        return on_step(self)

    monkeypatch.setattr(training._RunMonitor, "_on_step", ctrl_c_once)
    out = tmp_path / "run"
    code, output = run("train", *TINY, "--timesteps", "1024", "--eval-every", "1024", "--out", out)
    assert code == 130 and sent, output
    assert "its last checkpoint is at step 512" in output and f"socnav train --resume {out}" in output
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back
    monkeypatch.undo()
    code, output = run("train", "--resume", out)
    assert code == 0, output
    assert "from step 512 of 1,024" in output


def test_ctrl_c_in_evaluate_writes_the_finished_episodes(monkeypatch, tmp_path):
    from contextlib import contextmanager

    @contextmanager
    def ctrl_c_after_five(label, total):
        done = []

        def advance(n):
            done.append(n)
            if sum(done) >= 5:
                raise KeyboardInterrupt

        yield advance

    monkeypatch.setattr("socnav.cli.common.progress_bar", ctrl_c_after_five)
    out = tmp_path / "part.csv"
    code, output = run("evaluate", "--controller", "orca", "--scenario", "circle_crossing", "--episodes", "200",
                       "--n-envs", "4", "--out", out)
    records = pd.read_csv(out)
    assert code == 130 and f"interrupted: wrote the {len(records)} finished episodes (of 200) to {out}" in output
    assert 5 <= len(records) < 200 and records["episode"].is_unique
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left: written atomically


def test_an_interrupted_rollout_carries_its_finished_records():
    import socnav
    from socnav.controllers import make_controller
    from socnav.envs.rollout import RolloutInterrupted, rollout_episodes

    config = socnav.load_config({"scenario": "circle_crossing", "n_humans": 3})
    calls = []

    def stop_at_three(n):
        calls.append(n)
        if sum(calls) >= 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as caught:  # still a KeyboardInterrupt for code that catches one
        rollout_episodes(make_controller("orca", config), config, 50, n_envs=4, progress=stop_at_three)
    assert isinstance(caught.value, RolloutInterrupted)
    assert len(caught.value.records) >= 3 and caught.value.asked == 50
    full = rollout_episodes(make_controller("orca", config), config, 50, n_envs=4)
    finished = caught.value.records.set_index("episode")
    pd.testing.assert_frame_equal(finished, full.set_index("episode").loc[finished.index])


def test_a_ctrl_c_that_numba_wraps_is_still_an_interruption():
    """A Ctrl-C that arrives while numba loads a compiled function from its cache surfaces as a SystemError caused by
    the KeyboardInterrupt (seen once in CI on `kill` of `socnav evaluate`): the rollout stops as for a Ctrl-C, with
    its finished records; a SystemError that no Ctrl-C caused is not swallowed."""
    import socnav
    from socnav.controllers import make_controller
    from socnav.envs.rollout import RolloutInterrupted, rollout_episodes

    config = socnav.load_config({"scenario": "circle_crossing", "n_humans": 3})
    calls = []

    def wrapped(interrupt: bool):
        def progress(n):
            calls.append(n)
            if sum(calls) >= 3:
                if not interrupt:
                    raise SystemError("a compiled function failed")
                try:
                    raise KeyboardInterrupt
                except KeyboardInterrupt as cause:
                    raise SystemError("returned a result with an exception set") from cause
        return progress

    with pytest.raises(RolloutInterrupted) as caught:
        rollout_episodes(make_controller("orca", config), config, 50, n_envs=4, progress=wrapped(True))
    assert len(caught.value.records) >= 3 and caught.value.asked == 50
    calls.clear()
    with pytest.raises(SystemError, match="a compiled function failed"):
        rollout_episodes(make_controller("orca", config), config, 50, n_envs=4, progress=wrapped(False))


# ------------------------------------------------------------------------------------------ --humans

def test_humans_option_sets_the_human_model(tmp_path, monkeypatch):
    out = tmp_path / "r.csv"
    code, output = run("evaluate", "--controller", "straight", "--scenario", "position_swap", "--humans",
                       "social_force", "--episodes", "2", "--out", out)
    assert code == 0, output
    assert "world: position_swap, 1 human, social_force humans" in output
    monkeypatch.setattr("socnav.rl.persistence.load_policy", _no_work)  # refused before a model loads
    for command in (["train", *TINY], ["evaluate", "--model", "pretrained"], ["animate", "--model", "pretrained"],
                    ["calibrate", "--model", "pretrained"], ["tune", "--algo", "ppo", "--scenario", "random",
                                                             "--trials", "1"]):
        code, output = run(*command, "--humans", "socail_force")
        assert code == 2 and "--humans" in output and "allowed: orca, social_force" in output, (command, output)
        assert "did you mean social_force" in output


# ------------------------------------------------------------------------------------------ dry run

def test_dry_run_refuses_what_the_run_refuses(tmp_path):
    from socnav.experiments.runner import prepare_run_dir
    from socnav.experiments.spec import load_experiment

    smoke = REPO / "configs" / "experiments" / "smoke.yaml"
    root = tmp_path / "run"
    prepare_run_dir(root, load_experiment(smoke, "quick"), smoke)
    before = sorted(p.name for p in root.iterdir())
    code, output = run("run", smoke, "--out", root, "--dry-run")  # the grid as written: another budget
    assert code == 2 and "holds experiment 'smoke' with budget 'quick'" in output and "pending" not in output
    assert sorted(p.name for p in root.iterdir()) == before  # nothing written
    code, output = run("run", smoke, "--budget", "quick", "--out", root, "--dry-run")
    assert code == 0 and "pending" in output
    afile = tmp_path / "afile"
    afile.write_text("x")
    code, output = run("run", smoke, "--budget", "quick", "--out", afile / "run", "--dry-run")
    assert code == 2 and "is a file" in output


# ------------------------------------------------------------------------------------------ world note

def test_a_policy_outside_its_training_world_gets_a_note(monkeypatch, tmp_path):
    monkeypatch.setattr("socnav.envs.rollout.rollout_episodes", _no_work)
    result = runner.invoke(app, ["evaluate", "--model", "pretrained", "--scenario", "corridor", "--n-humans", "1",
                                 "--out", str(tmp_path / "r.csv")])
    output = " ".join(result.output.split())
    assert isinstance(result.exception, WorkStarted), output
    assert ("note: pretrained runs outside the world it was trained in (scenario position_swap -> corridor; "
            "no walls -> walls)") in output
    result = runner.invoke(app, ["evaluate", "--model", "pretrained", "--out", str(tmp_path / "r.csv")])
    assert isinstance(result.exception, WorkStarted) and "note:" not in result.output


# ------------------------------------------------------------------------------------------ progress

def test_rollout_shows_progress_when_asked_or_in_a_terminal(monkeypatch, capsys):
    import socnav
    from socnav.controllers import make_controller
    from socnav.envs import rollout

    config = socnav.load_config({"scenario": "position_swap", "n_humans": 1})
    rollout.rollout_episodes(make_controller("straight", config), config, 3, progress=True)
    assert "3/3" in capsys.readouterr().err
    rollout.rollout_episodes(make_controller("straight", config), config, 3)  # no terminal here: silent
    assert capsys.readouterr().err == ""
    monkeypatch.setattr("sys.stderr.isatty", lambda: True, raising=False)
    assert rollout._show_progress(None, "__main__")  # your own code in a terminal
    assert not rollout._show_progress(None, "socnav.rl.training")  # socnav's callers show their own
    assert not rollout._show_progress(False, "__main__")


def test_readme_python_example_is_the_measured_example_file():
    """The README's Python example is examples/readme_example.py (measured: `time python examples/...`)."""
    readme = (REPO / "README.md").read_text()
    example = (REPO / "examples" / "readme_example.py").read_text()
    block = readme.split("```python\n", 1)[1].split("```", 1)[0]
    assert block.strip() in example


# ------------------------------------------------------------------------------------------ plot

def test_plot_draws_a_runs_training_curve(tmp_path):
    require("matplotlib")
    run_dir = _curve_run(tmp_path)
    code, output = run("plot", run_dir)
    assert code == 0, output
    png = run_dir / "curve.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"training curve: {png}" in output
    code, output = run("plot", run_dir)
    assert code == 2 and "exists; pass --force" in output
    assert run("plot", run_dir, "--force")[0] == 0
    code, output = run("plot", tmp_path / "nowhere")
    assert code == 2 and "no such run directory" in output
    code, output = run("plot", tmp_path)
    assert code == 2 and "has no curve.csv" in output
    code, output = run("plot", run_dir, "--out", tmp_path / "curve.jpg")
    assert code == 2 and ".png" in output


def test_a_config_error_found_when_the_world_is_built_is_one_line(tmp_path, monkeypatch, capsys):
    """Walls that cover every start are found only when episodes are drawn (inside the rollout): the `socnav`
    entry point still reports them in one line with exit code 2, not a traceback."""
    import sys

    from socnav.cli import main

    config = tmp_path / "covered.yaml"
    config.write_text("scenario: circle_crossing\nn_humans: 2\nobstacles:\n"
                      "  - [[-50, -50], [50, -50], [50, 50], [-50, 50]]\n")
    monkeypatch.setattr(sys, "argv", ["socnav", "evaluate", "--controller", "orca", "--config", str(config),
                                      "--episodes", "2", "--out", str(tmp_path / "r.csv")])
    with pytest.raises(SystemExit) as stop:
        main()
    assert stop.value.code == 2
    output = " ".join(capsys.readouterr().out.split())
    assert "error: scenario 'circle_crossing': no episode in 100 draws has every start and goal clear" in output
    assert "Traceback" not in output


@pytest.mark.heavy
@pytest.mark.parametrize("sigint", ["default", "ignored"])
def test_sigterm_keeps_the_finished_episodes_as_ctrl_c_does(tmp_path, sigint):
    """`kill` (SIGTERM) on a long `socnav evaluate` is handled as the first Ctrl-C: the finished episodes are written
    and the command stops with exit code 130 -- also when it started with SIGINT ignored, as a background job of a
    non-interactive shell does (SIGTERM used to raise the ignored SIGINT, and the command ran on)."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "part.csv"
    start = signal.SIG_IGN if sigint == "ignored" else signal.SIG_DFL  # SIG_DFL: Python installs its own handler
    process = subprocess.Popen([sys.executable, "-m", "socnav", "evaluate", "--controller", "orca", "--episodes",
                                "500000", "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, start))
    try:
        time.sleep(20)  # imports and the world built (a few seconds); the 500,000 episodes take minutes
        assert process.poll() is None, "the evaluation ended before it was signalled"
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 130, output
    assert "interrupted: wrote the" in " ".join(output.split())
    assert out.is_file() and out.stat().st_size > 0
