"""Mistakes a new user makes get one clear line instead of a traceback, refused before any work is done, and the
output says what actually happens (a rollout larger than the budget, where a stopped training can continue, the
world a model plays in)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _extras import require
from typer.testing import CliRunner

import socnav
from socnav.cli import app

REPO = Path(__file__).resolve().parents[1]
runner = CliRunner()


def run(*args: object) -> tuple[int, str]:
    result = runner.invoke(app, [str(a) for a in args])
    assert "Traceback" not in result.output, result.output
    if result.exit_code not in (0, 2, 130):  # an exception escaped: show it
        raise AssertionError(f"exit {result.exit_code}: {result.exception!r}\n{result.output}")
    return result.exit_code, " ".join(result.output.split())


class WorkStarted(Exception):
    """Raised by a patched step: the command went on to the work it should have refused before."""


def _no_work(*args, **kwargs):
    raise WorkStarted("the command started its work")


@pytest.fixture
def afile(tmp_path) -> Path:
    path = tmp_path / "afile"
    path.write_text("a file, not a directory")
    return path


def _policy(tmp_path: Path, algo: str, env: dict, name: str) -> Path:
    from socnav.rl import make_model
    from socnav.rl.persistence import save_policy

    model = make_model(algo, socnav.make_vec_env(env, n_envs=1), seed=0)
    metadata = {"algo": algo, "algo_config": model.algo_config, "env_config": socnav.load_config(env).model_dump(
        mode="json")}
    return save_policy(model.policy, tmp_path / name, metadata)


# ------------------------------------------------------------------------------------------ caps and bad input files

@pytest.mark.parametrize("command", [["evaluate"], ["calibrate", "--model", "pretrained"], ["demo"]])
def test_episodes_have_the_experiment_files_cap(monkeypatch, command):
    from socnav.experiments.spec import MAX_EPISODES

    monkeypatch.setattr("socnav.envs.rollout.rollout_episodes", _no_work)
    monkeypatch.setattr("socnav.cli.workflows.demo.baseline_rows", _no_work)
    monkeypatch.setattr("socnav.safety.calibrate_thresholds", _no_work)
    code, output = run(*command, "--episodes", MAX_EPISODES * 10)
    assert code == 2 and "--episodes" in output and f"{MAX_EPISODES}" in output


@pytest.mark.parametrize("content, words", [
    (b"scenario: circle_crossing\nn_humans: " + b"7" * 5000 + b"\n", "4,300 digits"),
    (bytes(range(256)) * 8, "not UTF-8"),
])
def test_a_config_file_yaml_cannot_build_is_one_line(tmp_path, content, words):
    path = tmp_path / "env.yaml"
    path.write_bytes(content)
    code, output = run("evaluate", "--config", path, "--episodes", "1", "--out", tmp_path / "r.csv")
    assert code == 2 and words in output and str(path) in output


def test_a_huge_number_given_with_set_is_one_line():
    code, output = run("train", "--set", "n_steps=" + "1" * 5000)
    assert code == 2 and "--set" in output and "4,300 digits" in output


def test_config_from_proc_or_a_device_is_one_line(tmp_path):
    code, output = run("evaluate", "--config", "/dev/zero", "--episodes", "1", "--out", tmp_path / "r.csv")
    assert code == 2 and "/dev/zero is not a regular file" in output
    code, output = run("evaluate", "--config", "/proc/self/status", "--episodes", "1", "--out", tmp_path / "r.csv")
    assert code == 2 and "/proc/self/status is not valid YAML" in output


@pytest.mark.parametrize("option", [["evaluate", "--config"], ["train", "--algo-config"],
                                    ["evaluate", "--model"], ["evaluate", "--model", "pretrained", "--safety"],
                                    ["run"]])
def test_a_directory_where_a_file_is_expected_says_so(tmp_path, option):
    code, output = run(*option, tmp_path, "--episodes", "1") if option[0] == "evaluate" else run(*option, tmp_path)
    assert code == 2 and "is a directory" in output and "not found" not in output


def test_a_file_given_to_resume_says_so(afile):
    code, output = run("train", "--resume", afile)
    assert code == 2 and "is a file" in output


# ------------------------------------------------------------------------------------------ outputs checked first

@pytest.mark.parametrize("command", [
    ["evaluate", "--episodes", "1", "--out", "{afile}/r.csv"],
    ["calibrate", "--model", "pretrained", "--episodes", "1", "--out", "{afile}/t.yaml"],
    ["animate", "--model", "pretrained", "--out", "{afile}/a.gif"],
    ["train", "--timesteps", "64", "--out", "{afile}/run"],
    ["convert", "pretrained", "--to-sb3", "{afile}/sb3.zip"],
    ["demo", "--out", "{afile}"],
    ["evaluate", "--episodes", "1", "--out", "/proc/socnav-records.csv"],
])
def test_an_output_that_cannot_be_written_is_refused_before_the_work(monkeypatch, afile, command):
    for target in ("socnav.envs.rollout.rollout_episodes", "socnav.cli.workflows.demo.baseline_rows",
                   "socnav.safety.calibrate_thresholds", "socnav.cli.workflows.animation.animate_episode",
                   "socnav.rl.training.train", "socnav.rl.convert.to_sb3"):
        monkeypatch.setattr(target, _no_work)
    code, output = run(*(part.format(afile=afile) for part in command))
    # socnav.io.check_output_file's words for a file among the parents and for /proc; `train` and `demo` (run
    # directories) keep their own
    assert code == 2 and any(words in output for words in ("is a file", "is an existing file", "cannot write",
                                                            "is not a directory", "a system path")), output


def test_animate_mp4_without_the_video_extra_is_refused_before_playing(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # as if the [video] extra were not installed
    monkeypatch.setattr("socnav.cli.workflows.animation.animate_episode", _no_work)
    code, output = run("animate", "--model", "pretrained", "--out", tmp_path / "x.mp4")
    assert code == 2 and "imageio-ffmpeg" in output and "[video]" in output


def test_export_without_its_extra_gives_the_install_hint(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "onnx", None)
    code, output = run("export", "pretrained", "--out", tmp_path / "n.onnx")
    assert code == 2 and '[export]' in output and "pip install" in output


def test_tune_storage_that_is_not_a_url_is_one_line(tmp_path):
    require("optuna")
    result = runner.invoke(app, ["tune", "--algo", "ppo", "--scenario", "position_swap", "--trials", "1",
                                 "--storage", "notaurl", "--out", str(tmp_path / "trials")])
    output = " ".join(result.output.split())
    assert isinstance(result.exception, SystemExit) and result.exit_code != 0, output
    assert "notaurl" in output and "sqlite:///" in output and "Traceback" not in output


def test_bench_env_without_pyrvo_is_one_line():
    benchmarks = REPO / "benchmarks"  # on sys.path, as when the script is run: `python benchmarks/bench_env.py`
    code = ("import runpy, sys; sys.modules['pyrvo'] = None; sys.argv = ['bench_env.py', '--quick']; "
            f"sys.path.insert(0, {str(benchmarks)!r}); "
            f"runpy.run_path({str(benchmarks / 'bench_env.py')!r}, run_name='__main__')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode != 0 and "Traceback" not in out.stderr, out.stderr
    assert 'pip install "pyrvo' in out.stderr


# ------------------------------------------------------------------------------------------ Ray with nothing there

def test_ray_address_with_nothing_listening_fails_fast_with_one_line(tmp_path):
    from socnav.experiments.backends import _probe_ray_address
    from socnav.experiments.runner import RunnerError

    started = time.perf_counter()
    with pytest.raises(RunnerError, match="nothing accepts connections"):
        _probe_ray_address("127.0.0.1:1")
    with pytest.raises(RunnerError, match="not a Ray address"):
        _probe_ray_address("127.0.0.1")
    assert time.perf_counter() - started < 30


@pytest.fixture
def silent_grpc_port():
    """A port that accepts connections and opens HTTP/2 as a gRPC server would, then says nothing more (a proxy,
    another service): ray.init retries such an address for many minutes inside native code."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))
    connections = []

    def serve() -> None:
        while True:
            try:
                connection, _ = server.accept()
                connections.append(connection)
                connection.sendall(bytes([0, 0, 0, 4, 0, 0, 0, 0, 0]))  # an empty SETTINGS frame
            except OSError:
                return

    threading.Thread(target=serve, daemon=True).start()
    yield server.getsockname()[1]
    server.close()
    for connection in connections:
        connection.close()


def test_an_address_where_no_ray_answers_gives_up_within_the_timeout(silent_grpc_port):
    from socnav.experiments.backends import _check_ray_connects
    from socnav.experiments.runner import RunnerError

    require("ray")
    started = time.perf_counter()
    with pytest.raises(RunnerError, match="cannot connect to the Ray cluster"):
        _check_ray_connects(f"127.0.0.1:{silent_grpc_port}", timeout=20)
    assert time.perf_counter() - started < 45


@pytest.mark.heavy
def test_ctrl_c_while_connecting_to_ray_exits_promptly(tmp_path, silent_grpc_port):
    import os
    import signal

    require("ray")
    command = [sys.executable, "-m", "socnav", "run", str(REPO / "configs" / "experiments" / "smoke.yaml"),
               "--budget", "quick", "--backend", "ray", "--address", f"127.0.0.1:{silent_grpc_port}", "--out",
               str(tmp_path / "run")]
    # As a terminal starts a foreground job: its own process group, Ctrl-C at its default action. A process that
    # ignores SIGINT passes that on to its children, so this test must not depend on what the test process inherited.
    sweep = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))

    def connecting() -> bool:  # the sweep has started its connection attempt (a child process running ray.init)
        for status in Path("/proc").glob("[0-9]*/cmdline"):
            try:
                if b"ray.init(address=" in status.read_bytes() and os.getpgid(int(status.parent.name)) == sweep.pid:
                    return True
            except OSError:
                continue
        return False

    try:
        deadline = time.monotonic() + 90  # then it is connecting, whichever way it does
        while not connecting() and time.monotonic() < deadline:
            assert sweep.poll() is None, sweep.communicate()[0]
            time.sleep(0.2)
        time.sleep(2)
        os.killpg(sweep.pid, signal.SIGINT)  # Ctrl-C reaches the terminal's whole foreground group
        output, _ = sweep.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail("socnav run did not exit within 30 s of Ctrl-C while connecting to Ray")
    finally:
        if sweep.poll() is None:
            os.killpg(sweep.pid, signal.SIGKILL)
    assert sweep.returncode == 130 and "interrupted" in output and "Traceback" not in output, output


@pytest.mark.heavy
def test_run_on_a_ray_address_with_nothing_listening_exits_in_bounded_time(tmp_path):
    require("ray")
    command = [sys.executable, "-m", "socnav", "run", str(REPO / "configs" / "experiments" / "smoke.yaml"),
               "--budget", "quick", "--backend", "ray", "--address", "127.0.0.1:1", "--out", str(tmp_path / "run")]
    try:
        out = subprocess.run(command, capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        pytest.fail("socnav run --backend ray --address 127.0.0.1:1 did not give up within 120 s")
    assert out.returncode == 2 and "Traceback" not in out.stdout + out.stderr
    assert "127.0.0.1:1" in out.stdout and "nothing accepts connections" in " ".join(out.stdout.split())


# ------------------------------------------------------------------------------------------ train says what happens

TINY = ["--scenario", "position_swap", "--n-humans", "1", "--algo", "ppo", "--n-envs", "2", "--eval-episodes", "1"]


def test_a_rollout_larger_than_the_budget_is_said_before_training(tmp_path):
    code, output = run("train", *TINY, "--timesteps", "100", "--out", tmp_path / "run")
    assert code == 0, output
    assert "256 steps will be trained" in output and "100 asked" in output
    assert output.index("whole rollouts") < output.index("(validation)")  # before the result, not after it


def test_ctrl_c_in_train_says_where_it_stopped_and_how_to_resume(monkeypatch, tmp_path):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("socnav.rl.training.train", interrupted)
    out = tmp_path / "run"
    code, output = run("train", *TINY, "--timesteps", "128", "--out", out)
    assert code == 130 and "interrupted" in output and f"socnav train --resume {out}" in output


def test_resume_refuses_options_it_would_ignore(tmp_path):
    code, output = run("train", "--resume", tmp_path, "--timesteps", "1000", "--seed", "3")
    assert code == 2 and "--timesteps" in output and "--seed" in output and "ignored" in output


@pytest.mark.heavy
def test_resume_says_the_step_it_resumes_from(tmp_path):
    out = tmp_path / "run"
    code, output = run("train", *TINY, "--timesteps", "512", "--eval-every", "256", "--set", "n_steps=128", "--out",
                       out)
    assert code == 0, output
    (out / "model.zip").unlink()  # as a kill after the last checkpoint leaves the run
    info = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**info, "status": "running"}))
    code, output = run("train", "--resume", out)
    assert code == 0, output
    assert "from step 512 of 512" in output


# ------------------------------------------------------------------------------------------ models and their worlds

def test_max_humans_hint_with_a_model_leads_to_a_command_that_works(tmp_path):
    common = ["evaluate", "--model", "pretrained", "--scenario", "circle_crossing", "--episodes", "1"]
    code, output = run(*common, "--n-humans", "12", "--out", tmp_path / "a.csv")
    assert code == 2 and "--n-humans 10 or fewer" in output and "--max-humans 12" not in output
    code, output = run(*common, "--n-humans", "10", "--out", tmp_path / "b.csv")
    assert code == 0, output
    code, output = run(*common, "--n-humans", "3", "--max-humans", "12", "--out", tmp_path / "c.csv")
    assert code == 2 and "use --max-humans 10" in output
    code, output = run(*common, "--n-humans", "3", "--max-humans", "10", "--out", tmp_path / "d.csv")
    assert code == 0, output


def test_animate_and_calibrate_play_the_model_in_its_own_world(monkeypatch, tmp_path):
    model = _policy(tmp_path, "odv-ppo-drop", {"scenario": "circle_crossing", "n_humans": 2}, "crossing.zip")
    worlds = []

    def record(policy, estimator, config, *args, **kwargs):
        worlds.append(socnav.load_config(config))
        raise WorkStarted("recorded")

    monkeypatch.setattr("socnav.cli.workflows.animation.animate_episode", record)
    monkeypatch.setattr("socnav.safety.calibrate_thresholds", record)
    for command in (["animate", "--out", tmp_path / "a.gif"], ["calibrate", "--out", tmp_path / "t.yaml"]):
        result = runner.invoke(app, [str(part) for part in (*command, "--model", model, "--k", "2")])
        assert isinstance(result.exception, WorkStarted), result.output
        assert "world: circle_crossing, 2 humans (the model's training world)" in " ".join(result.output.split())
    assert [(world.scenario, world.n_humans) for world in worlds] == [("circle_crossing", 2)] * 2


def test_animate_draws_no_mc_dropout_bars_for_a_model_without_dropout(monkeypatch, tmp_path):
    model = _policy(tmp_path, "ppo", {"scenario": "position_swap", "n_humans": 1}, "ppo.zip")
    estimators = []

    def record(policy, estimator, *args, **kwargs):
        estimators.append(estimator)
        return tmp_path / "a.gif", {"outcome": "goal", "length": 1, "fallback_steps": None}

    monkeypatch.setattr("socnav.cli.workflows.animation.animate_episode", record)
    code, output = run("animate", "--model", model, "--out", tmp_path / "a.gif")
    assert code == 0 and estimators == [None] and "no uncertainty bars" in output
    code, output = run("animate", "--model", model, "--safety", "mc", "--out", tmp_path / "b.gif")
    assert code == 2 and "dropout" in output
    code, output = run("calibrate", "--model", model, "--out", tmp_path / "t.yaml")
    assert code == 2 and "dropout" in output


# ------------------------------------------------------------------------------------------ remaining one-liners

def test_a_directory_given_as_thresholds_to_the_python_api_says_so(tmp_path):
    from socnav.safety import ThresholdsError, load_thresholds

    with pytest.raises(ThresholdsError, match="is a directory, not a thresholds file"):
        load_thresholds(tmp_path)


def test_report_out_under_a_file_is_one_line(afile, tmp_path):
    from socnav.experiments.runner import prepare_run_dir
    from socnav.experiments.spec import load_experiment

    smoke = REPO / "configs" / "experiments" / "smoke.yaml"
    root = tmp_path / "run"
    prepare_run_dir(root, load_experiment(smoke, "quick"), smoke)  # a run directory with nothing done yet
    code, output = run("report", root, "--out", afile / "report")
    assert code == 2 and "cannot write the report" in output and str(afile) in output


def test_tune_caps_its_counts_like_the_experiment_files(tmp_path):
    from socnav.experiments.spec import MAX_EPISODES

    code, output = run("tune", "--algo", "ppo", "--scenario", "circle_crossing", "--trials", "1",
                       "--eval-episodes", MAX_EPISODES * 10, "--storage", f"sqlite:///{tmp_path}/t.db")
    assert code == 2 and "--eval-episodes" in output and f"{MAX_EPISODES}" in output


def test_ctrl_c_while_ray_imports_exits_130_without_a_traceback(monkeypatch, tmp_path):
    import builtins

    real_import = builtins.__import__

    def interrupted(name, *args, **kwargs):
        if name == "ray":
            raise KeyboardInterrupt
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", interrupted)
    code, output = run("run", REPO / "configs" / "experiments" / "smoke.yaml", "--budget", "quick", "--backend",
                       "ray", "--out", tmp_path / "run")
    assert code == 130 and "interrupted" in output
