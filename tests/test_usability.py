"""What a new user would trip over, kept from happening: results never overwrite each other, output says what it
means, the options a user looks for exist. Each test checks the behaviour a user of SB3 / rl-zoo / CrowdNav would
expect against an independent truth."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from _extras import require
from typer.testing import CliRunner

import socnav
from socnav.cli import app

REPO = Path(__file__).resolve().parents[1]
runner = CliRunner()


def run(*args: object) -> tuple[int, str]:
    result = runner.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


def flat(text: str) -> str:
    return " ".join(text.split())


def socnav_process(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """`python -m socnav ARGS` with stdout piped (not a terminal), as `socnav ... | less` runs it."""
    return subprocess.run([sys.executable, "-m", "socnav", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300)


# ------------------------------------------------------------------------------------------ entry points, help

def test_python_m_socnav_version_and_help_without_type_noise():
    version = socnav_process("--version")
    assert version.returncode == 0 and version.stdout.strip() == f"socnav {socnav.__version__}"
    help_text = socnav_process("evaluate", "--help")
    assert help_text.returncode == 0
    assert "Usage: socnav evaluate" in help_text.stdout  # the command's name, not __main__.py
    assert "--stochastic / --no-stochastic" in help_text.stdout and "<bool>" not in help_text.stdout


def test_cli_module_does_not_import_torch_or_sb3():
    # `socnav --help` imports socnav.cli and nothing heavy: torch and SB3 load inside the commands that use them.
    code = ("import sys, socnav.cli; "
            "print(sorted(m for m in ('torch', 'stable_baselines3') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_gymnasium_make_without_importing_socnav_as_the_docs_say():
    # Gymnasium >= 1.0 has no plugin entry points; `module:id` imports the module that registers the id.
    snippet = 'gymnasium.make("socnav:socnav/CircleCrossing-v0", n_humans=3)'
    assert snippet in (REPO / "docs" / "index.md").read_text()  # Getting started, "Python"
    code = f"import sys, gymnasium; env = {snippet}; env.reset(seed=0); print(env.unwrapped.config.n_humans)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "3"


# ------------------------------------------------------------------------------------------ errors

def test_misspelt_field_suggests_the_nearest_one(tmp_path):
    config = tmp_path / "env.yaml"
    config.write_text("scenario: circle_crossing\nn_human: 3\n")
    code, output = run("evaluate", "--config", config, "--episodes", "1")
    assert code == 2 and "did you mean n_humans" in output
    assert "robot_orca_safety_margin" not in output  # not the list of every field


def test_too_many_humans_names_the_flag_that_raises_max_humans(tmp_path):
    code, output = run("evaluate", "--scenario", "circle_crossing", "--n-humans", "12", "--episodes", "1",
                       "--out", tmp_path / "r.csv")
    assert code == 2 and "--max-humans 12" in output
    code, output = run("evaluate", "--scenario", "circle_crossing", "--n-humans", "12", "--max-humans", "12",
                       "--episodes", "1", "--out", tmp_path / "r.csv")
    assert code == 0, output
    assert "12 humans" in output


# ------------------------------------------------------------------------------------------ evaluate

def test_default_record_files_are_unique_per_policy_world_seed_and_episodes(tmp_path, monkeypatch):
    from socnav.rl.persistence import pretrained_path

    monkeypatch.chdir(tmp_path)
    for directory in ("a", "b"):  # two runs, both with a model.zip, as `socnav train` writes them
        (tmp_path / directory).mkdir()
        shutil.copy(pretrained_path(), tmp_path / directory / "model.zip")
    invocations = [
        (["--controller", "straight", "--scenario", "circle_crossing", "--episodes", "3"], 3),
        (["--controller", "straight", "--config", REPO / "configs/env/circle_crossing_invisible.yaml",
          "--episodes", "4"], 4),
        (["--controller", "straight", "--scenario", "circle_crossing", "--episodes", "5"], 5),
        (["--model", "a/model.zip", "--episodes", "2"], 2),
        (["--model", "b/model.zip", "--episodes", "2"], 2),
    ]
    outputs = []
    for args, _ in invocations:
        code, output = run("evaluate", *args)
        assert code == 0, output
        outputs.append(flat(output))
    files = sorted((tmp_path / "runs" / "evaluate").iterdir())
    assert len(files) == len(invocations)  # nothing overwritten
    assert sorted(len(pd.read_csv(f)) for f in files) == sorted(n for _, n in invocations)
    assert "a/model.zip" in outputs[3] and "b/model.zip" in outputs[4]  # models named by their file


def test_model_is_evaluated_in_its_own_training_world(tmp_path):
    from socnav.envs.rollout import rollout_episodes

    policy = socnav.load_policy("pretrained")
    trained_in = socnav.load_config(policy.socnav_metadata["env_config"])
    code, output = run("evaluate", "--model", "pretrained", "--episodes", "3", "--out", tmp_path / "r.csv")
    assert code == 0, output
    low, _ = trained_in.humans_range()
    assert f"world: {trained_in.scenario}, {low} human" in flat(output)
    expected = rollout_episodes(policy, trained_in, 3, seed=0)
    np.testing.assert_allclose(pd.read_csv(tmp_path / "r.csv")["return"], expected["return"])


def test_evaluate_perturbation_and_safety_layer(tmp_path):
    from socnav.safety import Thresholds, save_thresholds

    never = save_thresholds(Thresholds.never(), tmp_path / "never.yaml")
    common = ["evaluate", "--model", "pretrained", "--episodes", "4", "--k", "2"]
    code, output = run(*common, "--out", tmp_path / "clean.csv")
    assert code == 0, output
    code, output = run(*common, "--perturb", "heading_noise=0.6", "--out", tmp_path / "plain.csv")
    assert code == 0 and "heading_noise=0.6" in output, output
    code, output = run(*common, "--perturb", "heading_noise=0.6", "--safety", never, "--out", tmp_path / "never.csv")
    assert code == 0, output
    assert "fallback % steps" in output
    clean, plain, never_fires = (pd.read_csv(tmp_path / f"{name}.csv") for name in ("clean", "plain", "never"))
    assert not np.allclose(clean["return"], plain["return"])  # the perturbation acts
    # A rule that never fires leaves the policy alone: the same episodes exactly, no fallback step.
    np.testing.assert_allclose(never_fires["return"], plain["return"])
    assert (never_fires["fallback_steps"] == 0).all()

    code, output = run(*common, "--perturb", "heading_noise=0.6", "--safety", "mc", "--out", tmp_path / "mc.csv")
    assert code == 0, output
    safe = pd.read_csv(tmp_path / "mc.csv")
    assert ((safe["fallback_steps"] >= 0) & (safe["fallback_steps"] <= safe["length"])).all()
    share = 100 * safe["fallback_steps"].sum() / safe["length"].sum()
    assert f"{share:.1f} │" in output  # the fallback-activation column

    code, output = run("evaluate", "--controller", "orca", "--safety", "mc", "--episodes", "1")
    assert code == 2 and "--model" in output


def test_evaluate_table_has_nav_time_and_says_what_pv_counts(tmp_path):
    code, output = run("evaluate", "--controller", "orca", "--scenario", "position_swap", "--episodes", "5",
                       "--out", tmp_path / "r.csv")
    assert code == 0, output
    records = pd.read_csv(tmp_path / "r.csv")
    nav_time = records.loc[records["outcome"] == "goal", "time_to_goal"].mean()
    assert "nav time (s)" in output and f"{nav_time:.1f} │" in output
    assert "PV: personal-space violations (intrusion events) per 200 episodes" in flat(output)


def test_piped_tables_keep_words_whole(tmp_path):
    out = socnav_process("evaluate", "--model", "pretrained", "--episodes", "2", "--k", "2",
                         "--perturb", "heading_noise=0.4", "--safety", "mc", "--out", str(tmp_path / "r.csv"))
    assert out.returncode == 0, out.stderr
    for words in ("fallback % steps", "nav time (s)", "PV/200 ep.", "pretrained + safety (mc)", "heading_noise=0.4"):
        assert words in out.stdout


# ------------------------------------------------------------------------------------------ tune

def test_install_hint_keeps_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "optuna", None)  # as if Optuna were not installed
    code, output = run("tune", "--algo", "ppo", "--scenario", "position_swap", "--trials", "1")
    assert code != 0
    assert '".[tune]"' in output or '"socnav[tune]"' in output
    # the guide's example (Experiments and reproduction, "Running experiments") says so
    assert "[tune]" in (REPO / "docs" / "reproduction.md").read_text().split("socnav tune")[1][:400]


def test_tune_continued_study_explores_and_refuses_other_settings(tmp_path):
    optuna = require("optuna")
    storage = f"sqlite:///{tmp_path / 'tune.db'}"
    common = ["tune", "--algo", "ppo", "--scenario", "position_swap", "--n-envs", "1", "--eval-episodes", "1",
              "--storage", storage, "--out", tmp_path / "trials"]
    code, output = run(*common, "--trials", "2", "--timesteps", "64")
    assert code == 0, output
    code, output = run(*common, "--trials", "2", "--timesteps", "64")
    assert code == 0, output
    trials = optuna.load_study(study_name="ppo_position_swap", storage=storage).trials
    assert len(trials) == 4
    assert trials[2].params != trials[0].params and trials[3].params != trials[1].params

    code, output = run(*common, "--trials", "1", "--timesteps", "128")
    assert code != 0 and "timesteps" in output and "--study-name" in output
    assert len(optuna.load_study(study_name="ppo_position_swap", storage=storage).trials) == 4


# ------------------------------------------------------------------------------------------ calibrate

def test_clopper_pearson_bound_is_exact_and_not_zero_after_zero_events():
    from scipy.stats import binom

    from socnav.safety.calibration import clopper_pearson_upper, false_activation_upper

    for events, trials in ((0, 50), (0, 1000), (3, 200), (40, 400)):
        upper = clopper_pearson_upper(events, trials, 0.95)
        assert binom.cdf(events, trials, upper) == pytest.approx(0.05, abs=1e-9)  # the defining equation
    assert clopper_pearson_upper(0, 1000) == pytest.approx(1 - 0.05 ** (1 / 1000))
    assert clopper_pearson_upper(7, 7) == 1.0
    # No fallback on 600 unperturbed steps of 10 identical episodes: the normal bound would be 0.
    scores = {"false_activation_rate": 0.0, "false_activation_se": 0.0, "false_activation_steps": 0,
              "unperturbed_steps": 600}
    assert false_activation_upper(scores, 0.95) == pytest.approx(1 - 0.05 ** (1 / 600))
    assert false_activation_upper(scores, 0.5) == 0.0  # the documented point-estimate setting


def test_calibrate_shows_progress_and_warns_about_few_collisions(tmp_path):
    out = tmp_path / "mc.yaml"
    # the PPO policy collides in two calibration episodes: the chosen thresholds have a false-activation bound to show
    code, output = run("calibrate", "--model", "pretrained-ppo", "--episodes", "2", "--k", "2", "--out", out)
    assert code == 0, output
    done = re.findall(r"(\d+)/(\d+)", output)
    assert done and done[-1][0] == done[-1][1]  # a bar with counts, ending full
    assert "ETA" in output
    report = json.loads(out.with_suffix(".report.json").read_text())
    assert "(≤ 0.0%)" not in output
    if 0 < report["n_collisions"] < 10:
        assert "warning" in output and f"only {report['n_collisions']} calibration collision" in flat(output)


# ------------------------------------------------------------------------------------------ train, animate

def test_resume_of_a_finished_run_says_it_is_complete(tmp_path):
    out = tmp_path / "run"
    code, output = run("train", "--scenario", "position_swap", "--n-humans", "1", "--algo", "ppo", "--timesteps",
                       "100", "--n-envs", "2", "--eval-episodes", "1", "--out", out)
    assert code == 0, output
    trained = json.loads((out / "run.json").read_text())["num_timesteps"]
    assert trained == 256  # one rollout of n_steps 128 x 2 environments
    assert "100 asked" in flat(output) and "whole rollouts" in flat(output)
    code, output = run("train", "--resume", out)
    assert code == 0, output
    assert "already complete" in flat(output) and not re.search(r"\b0/[\d,]+ steps", output)  # no empty bar
    assert json.loads((out / "run.json").read_text())["num_timesteps"] == trained


def test_animate_mentions_the_fallback_only_with_a_safety_layer(tmp_path):
    code, output = run("animate", "--model", "pretrained", "--k", "2", "--out", tmp_path / "a.gif")
    assert code == 0, output
    assert "fallback" not in output
    code, output = run("animate", "--model", "pretrained", "--k", "2", "--safety", "mc", "--out", tmp_path / "b.gif")
    assert code == 0, output
    assert re.search(r"safety fallback on \d+ steps", output)


def test_animate_plays_a_trigger_file_as_its_safety_layer(tmp_path):
    """`--safety` takes a trigger file (socnav calibrate --trigger) as `evaluate` does, not only the rule's
    thresholds: a time-to-collision trigger that fires whenever the policy's intended velocity leads into the human
    takes over in episode 6 of position swap (19 steps of it in `socnav evaluate --episodes 10`)."""
    trigger = tmp_path / "ttc.yaml"
    trigger.write_text("trigger: time-to-collision\nthreshold: -1000000.0\n")
    code, output = run("animate", "--model", "pretrained", "--safety", trigger, "--seed", "6",
                       "--out", tmp_path / "a.gif")
    assert code == 0, output
    steps = re.search(r"safety fallback on (\d+) steps", output)
    assert steps is not None and int(steps.group(1)) > 0, output


# ------------------------------------------------------------------------------------------ SB3 interoperability

def test_socnav_policy_file_becomes_a_full_sb3_model(tmp_path):
    from socnav.rl import ODVPPO
    from socnav.rl.convert import to_sb3

    policy = socnav.load_policy("pretrained")
    model = to_sb3("pretrained", n_envs=2)
    assert isinstance(model, ODVPPO)
    obs = socnav.make_vec_env(policy.socnav_metadata["env_config"], n_envs=4).reset()
    expected, _ = policy.predict(obs, deterministic=True)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], expected)

    code, output = run("convert", "pretrained", "--to-sb3", tmp_path / "sb3.zip")
    assert code == 0, output
    loaded = ODVPPO.load(tmp_path / "sb3.zip")  # SB3's own loader reads it
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], expected)
    model.learn(total_timesteps=16)  # fine-tuning runs
    assert model.num_timesteps > 0


def test_report_says_when_the_budget_differs_from_the_papers():
    from socnav.experiments.spec import load_experiment
    from socnav.paper.table1.comparison import budget_note

    smoke = load_experiment(REPO / "configs/experiments/smoke.yaml", "quick").model_dump(mode="json")
    note = budget_note(smoke)
    assert "budgets differ" in note and f"{smoke['grid']['timesteps']:,} steps" in note
    paper = load_experiment(REPO / "configs/experiments/table1.yaml", "paper").model_dump(mode="json")
    assert budget_note(paper) == ""
