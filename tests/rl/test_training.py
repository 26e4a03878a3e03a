"""Training runs and policy files: safe save/load, resume after a kill, the NaN stop, and the CLI around them."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch as th
from typer.testing import CliRunner

import socnav
from socnav.cli import app
from socnav.rl import make_model
from socnav.rl.persistence import PolicyLoadError, load_policy, save_policy
from socnav.rl.training import TrainingInterrupted, train

ENV = {"scenario": "position_swap", "n_humans": 1}
runner = CliRunner()


def _observations(n_envs: int = 6, seed: int = 3) -> dict[str, np.ndarray]:
    env = socnav.make_vec_env({"scenario": "circle_crossing", "n_humans": 4}, n_envs=n_envs)
    env.seed(seed)
    return env.reset()


def _saved(tmp_path: Path, algo: str = "odv-ppo-drop") -> tuple[object, Path]:
    model = make_model(algo, socnav.make_vec_env(ENV, n_envs=2), seed=1)
    metadata = {"algo": algo, "algo_config": model.algo_config,
                "env_config": socnav.load_config(ENV).model_dump(mode="json")}
    return model, save_policy(model.policy, tmp_path / "policy.zip", metadata)


@pytest.mark.parametrize("algo", ["ppo", "odv-ppo-drop"])
def test_save_load_predict_gives_identical_actions(tmp_path, algo):
    model, path = _saved(tmp_path, algo)
    model.policy.features_extractor.update_feature_range(th.randn(5, 64))
    path = save_policy(model.policy, path, json.loads(zipfile.ZipFile(path).read("socnav.json")))
    loaded = load_policy(path)
    obs = _observations()
    expected, _ = model.policy.predict(obs, deterministic=True)
    actions, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(actions, expected)
    assert loaded.socnav_metadata["algo"] == algo
    for mine, theirs in zip(model.policy.feature_range, loaded.feature_range, strict=True):
        assert th.equal(mine, theirs)
    assert not loaded.training  # dropout off after loading


def test_load_rejects_corrupted_and_foreign_files(tmp_path):
    _, good = _saved(tmp_path)
    data = good.read_bytes()

    truncated = tmp_path / "truncated.zip"
    truncated.write_bytes(data[: len(data) // 2])
    garbage = tmp_path / "garbage.zip"
    garbage.write_bytes(os.urandom(2048))
    sb3 = tmp_path / "sb3.zip"
    make_model("ppo", socnav.make_vec_env(ENV, n_envs=1), seed=0).save(sb3)  # SB3's pickling format
    wrong_format = tmp_path / "wrong_format.zip"
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(wrong_format, "w") as target:
        header = json.loads(source.read("socnav.json"))
        target.writestr("socnav.json", json.dumps({**header, "format": "something-else"}))
        target.writestr("policy.pt", source.read("policy.pt"))

    class Payload:  # an arbitrary object: torch.load(weights_only=True) must refuse to unpickle it
        def __reduce__(self):
            return (os.system, ("echo pwned",))

    pickled = tmp_path / "pickled.zip"
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(pickled, "w") as target:
        target.writestr("socnav.json", source.read("socnav.json"))
        buffer = __import__("io").BytesIO()
        th.save({"weights": Payload()}, buffer)
        target.writestr("policy.pt", buffer.getvalue())

    expected = {truncated: "corrupted", garbage: "corrupted", sb3: "SB3", wrong_format: "format",
                pickled: "tensors-only", tmp_path / "missing.zip": "no policy file"}
    for path, words in expected.items():
        with pytest.raises(PolicyLoadError, match=words):
            load_policy(path)


def test_evaluate_model_cli_and_clear_errors(tmp_path):
    _, path = _saved(tmp_path)
    out = tmp_path / "records.csv"
    result = runner.invoke(app, ["evaluate", "--model", str(path), "--scenario", "position_swap", "--n-humans", "1",
                                 "--episodes", "4", "--seed", "5", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert list(pd.read_csv(out)["seed"]) == [5, 6, 7, 8]
    result = runner.invoke(app, ["evaluate", "--model", str(tmp_path / "nope.zip"), "--episodes", "1"])
    assert result.exit_code == 2 and "no policy file" in result.output and "Traceback" not in result.output


def test_train_cli_rejects_bad_algo_and_overrides(tmp_path):
    result = runner.invoke(app, ["train", "--algo", "dqn", "--timesteps", "10", "--out", str(tmp_path / "a")])
    assert result.exit_code == 2 and "allowed: ppo, ppo-drop" in result.output
    result = runner.invoke(app, ["train", "--set", "learning_rat=1e-3", "--timesteps", "10",
                                 "--out", str(tmp_path / "b")])
    assert result.exit_code == 2 and "learning_rat" in result.output and "learning_rate" in result.output
    result = runner.invoke(app, ["train", "--set", "batch_size=0", "--timesteps", "10", "--out", str(tmp_path / "c")])
    assert result.exit_code == 2 and "batch_size" in result.output
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_train_writes_run_directory_and_loadable_model(tmp_path):
    seen: list[tuple[int, float]] = []
    result = train(ENV, "odv-ppo-drop", seed=2, timesteps=1024, out_dir=tmp_path, n_envs=4, eval_every=512,
                   eval_episodes=3, progress=lambda done, success: seen.append((done, success)))
    assert result.timesteps == 1024 and seen[-1][0] == 1024
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["status"] == "complete" and run["num_timesteps"] == 1024
    curve, evals = pd.read_csv(tmp_path / "curve.csv"), pd.read_csv(tmp_path / "eval.csv")
    assert list(curve["timesteps"]) == [512, 1024]
    assert list(evals["timesteps"]) == [512, 1024] and set(evals["episodes"]) == {3}
    assert any((tmp_path / "tb").rglob("events.out.tfevents*"))
    policy = load_policy(result.model_path)
    assert policy.socnav_metadata["timesteps"] == 1024
    assert th.isfinite(policy.feature_range[0]).all()  # tracked during the rollouts
    # eval.csv's values: every row is a distribution over the 3 validation episodes, and the last row (the final
    # model) is what an independent evaluation of the saved policy on the validation seeds gives.
    from socnav.envs.rollout import rollout_episodes, summarize
    from socnav.rl.training import VALIDATION_SEED_BASE

    assert list(evals[["goal_pct", "collision_pct", "timeout_pct"]].sum(axis=1)) == pytest.approx([100.0, 100.0])
    records = rollout_episodes(policy, ENV, 3, seed=VALIDATION_SEED_BASE)
    assert list(records["seed"]) == [VALIDATION_SEED_BASE + k for k in range(3)]
    expected = summarize(records)
    final = evals.iloc[-1]
    for column in ("episodes", "goal_pct", "collision_pct", "timeout_pct", "pv", "return_mean", "return_std"):
        assert final[column] == pytest.approx(expected[column], rel=1e-12, abs=1e-12), column
        assert result.final_eval[column] == expected[column], column
    assert expected["return_std"] > 0.0, "three identical episodes would not tell seeds apart"


def test_nan_stops_training_naming_step_and_tensor(tmp_path, monkeypatch):
    import socnav.rl.training as training

    real = training.make_vec_env

    def poisoned(config, n_envs):
        env = real(config, n_envs=n_envs)
        step_wait = env.step_wait

        def step_wait_with_nan():
            obs, reward, done, infos = step_wait()
            if env.world.steps.max() >= 40:
                obs["robot"][:] = np.nan
            return obs, reward, done, infos

        env.step_wait = step_wait_with_nan
        return env

    monkeypatch.setattr(training, "make_vec_env", poisoned)
    with pytest.raises(TrainingInterrupted, match=r"non-finite value in 'policy\.\w+' at timestep \d+"):
        train(ENV, "odv-ppo", seed=0, timesteps=2048, out_dir=tmp_path, n_envs=2, tensorboard=False)
    assert json.loads((tmp_path / "run.json").read_text())["status"] == "failed"


@pytest.mark.heavy
def test_killed_training_resumes_to_the_same_total(tmp_path):
    out = tmp_path / "run"
    command = [sys.executable, "-m", "socnav.cli", "train", "--scenario", "position_swap", "--n-humans", "1",
               "--algo", "odv-ppo-drop", "--timesteps", "6144", "--n-envs", "4", "--eval-every", "512",
               "--eval-episodes", "2", "--out", str(out)]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    state = out / "checkpoints" / "state.json"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and process.poll() is None:
        if state.is_file() and json.loads(state.read_text())["num_timesteps"] >= 1536:
            break
        time.sleep(0.05)
    assert process.poll() is None, "training finished before it could be killed; raise --timesteps"
    process.send_signal(signal.SIGKILL)
    process.wait()
    killed_at = json.loads(state.read_text())["num_timesteps"]
    assert 1536 <= killed_at < 6144

    resumed = subprocess.run([sys.executable, "-m", "socnav.cli", "train", "--resume", str(out)],
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "complete" and run["num_timesteps"] == 6144
    curve = pd.read_csv(out / "curve.csv")
    assert list(curve["timesteps"]) == list(range(512, 6144 + 1, 512))  # every rollout exactly once, in order
    evals = pd.read_csv(out / "eval.csv")
    assert list(evals["timesteps"]) == list(range(512, 6144 + 1, 512))
    assert load_policy(out / "model.zip").socnav_metadata["timesteps"] == 6144
    # the resumed run's checkpoint is the safe format (no SB3 pickles) and reloads to the same bytes
    from socnav.rl.persistence import load_checkpoint, save_checkpoint

    checkpoint = out / "checkpoints" / json.loads(state.read_text())["checkpoint"]
    assert set(zipfile.ZipFile(checkpoint).namelist()) == {"checkpoint.json", "state.pt"}
    model, header = load_checkpoint(checkpoint, socnav.make_vec_env(ENV, n_envs=4))
    assert header.num_timesteps == 6144 and header.run["curve_rows"] == len(curve)
    again = save_checkpoint(model, tmp_path / "again.zip", header.env_config, header.seed, header.run)
    assert again.read_bytes() == checkpoint.read_bytes()


def test_same_seed_gives_the_same_training_run(tmp_path):
    runs = [train(ENV, "odv-ppo-drop", seed=4, timesteps=1024, out_dir=tmp_path / name, n_envs=4, eval_every=512,
                  eval_episodes=2, tensorboard=False) for name in ("a", "b")]
    first, second = (load_policy(run.model_path).state_dict() for run in runs)
    assert all(th.equal(first[key], second[key]) for key in first)
    curves = [pd.read_csv(tmp_path / name / "curve.csv")["ep_rew_mean"] for name in ("a", "b")]
    assert curves[0].equals(curves[1])
