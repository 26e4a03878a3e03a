"""Run directories and input files an attacker or an accident shaped are handled safely: a symbolic link planted
in a run directory is never followed, a deep or huge JSON file gives one line and its unit is redone, a zip
is sized from its end record before `zipfile` parses it, a checkpoint's optimizer settings and counters are
cross-checked before a run resumes, and the Python API does not overwrite a run."""

from __future__ import annotations

import io
import json
import os
import shutil
import struct
import time
import zipfile
from pathlib import Path

import pandas as pd
import pytest
import torch as th
import yaml
from typer.testing import CliRunner

import socnav
from socnav.cli import app
from socnav.experiments.registry import EXECUTORS, ExecutorResult
from socnav.experiments.runner import RunnerError, read_plan, run_experiment, unit_states
from socnav.experiments.spec import PLANNERS, Unit, load_experiment
from socnav.io import UnsafePathError, UntrustedInputError, file_lock, parse_json, read_json
from socnav.rl.persistence import CheckpointError, PolicyLoadError, load_checkpoint, load_policy, pretrained_path
from socnav.rl.training import RunDirectoryExists, can_resume, move_run_aside, train

REPO = Path(__file__).resolve().parents[1]
SMOKE = REPO / "configs" / "experiments" / "smoke.yaml"
ENV = {"scenario": "position_swap", "n_humans": 1}
SMALL = {"n_steps": 64, "batch_size": 64, "n_epochs": 2}
TOTAL = 256
runner = CliRunner()


def _one_line_cli_error(result, *words: str) -> None:
    """Exit code 2, no traceback, the words in the output (rich may wrap: compared with whitespace joined)."""
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit) and "Traceback" not in result.output, result.output
    output = " ".join(result.output.split())
    for word in words:
        assert word in output, (word, result.output)


# ---------------------------------------------------------------------------------------------------------------
# A sweep of cheap units (no training): the runner's own handling of its directory
# ---------------------------------------------------------------------------------------------------------------

@pytest.fixture
def sweep(tmp_path, monkeypatch):
    """A two-unit experiment whose executor writes one file; returns (experiment, run root, calls)."""
    calls: list[str] = []

    def fine(root, unit, directory) -> ExecutorResult:
        calls.append(unit.id)
        (directory / "out.txt").write_text(f"result of {unit.id}")
        return ExecutorResult(["out.txt"])

    monkeypatch.setitem(PLANNERS, "links-demo", lambda experiment: [Unit("group/a", "fine", {"n": 1}),
                                                                     Unit("group/b", "fine", {"n": 2})])
    monkeypatch.setitem(EXECUTORS, "fine", fine)
    spec = {**yaml.safe_load(SMOKE.read_text()), "kind": "links-demo", "budgets": {}}
    (tmp_path / "demo.yaml").write_text(yaml.safe_dump(spec))
    return load_experiment(tmp_path / "demo.yaml"), tmp_path / "run", calls


def _victim(tmp_path: Path) -> tuple[Path, dict[Path, str]]:
    """A directory outside the run holding files someone cares about, laid out like a unit (so that following a
    link into it would find 'its' files); returns it and its files' contents."""
    victim = tmp_path / "victim"
    files = {victim / "a" / "precious.txt": "keep me", victim / "a" / "out.txt": "not a result",
             victim / "a" / ".out.txt.abcdefgh.tmp.txt": "looks like a temporary", victim / "precious.txt": "mine"}
    for path, text in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return victim, files


def _untouched(victim: Path, files: dict[Path, str]) -> None:
    assert sorted(p for p in victim.rglob("*") if p.is_file()) == sorted(files)
    assert all(path.read_text() == text for path, text in files.items())


def test_a_link_planted_above_the_units_is_replaced_never_followed(sweep, tmp_path):
    experiment, root, calls = sweep
    assert run_experiment(experiment, root, workers=0).ok
    victim, files = _victim(tmp_path)
    shutil.rmtree(root / "group")
    os.symlink(victim, root / "group")  # both units now 'live' in the victim directory

    states = unit_states(root, [Unit("group/a", "fine", {"n": 1})])
    assert states["group/a"] != "done"  # a unit reached through a link is not the run's own
    calls.clear()
    summary = run_experiment(experiment, root, workers=0)
    assert summary.ok and sorted(calls) == ["group/a", "group/b"], summary.outcomes
    assert not (root / "group").is_symlink() and (root / "group" / "a" / "out.txt").read_text() == "result of group/a"
    _untouched(victim, files)


def test_a_unit_directory_planted_as_a_link_to_a_finished_unit_is_redone(sweep, tmp_path):
    experiment, root, calls = sweep
    assert run_experiment(experiment, root, workers=0).ok
    copy = tmp_path / "copy"
    shutil.copytree(root / "group" / "a", copy)  # a finished unit, done.json and all, outside the run
    shutil.rmtree(root / "group" / "a")
    os.symlink(copy, root / "group" / "a")
    before = {path: path.read_bytes() for path in copy.iterdir()}

    calls.clear()
    assert run_experiment(experiment, root, workers=0).ok
    assert calls == ["group/a"]  # not skipped as done through the link
    assert not (root / "group" / "a").is_symlink() and (root / "group" / "a" / "done.json").is_file()
    assert {path: path.read_bytes() for path in copy.iterdir()} == before


def test_an_output_planted_as_a_link_makes_its_unit_corrupt(sweep, tmp_path):
    experiment, root, calls = sweep
    assert run_experiment(experiment, root, workers=0).ok
    output = root / "group" / "a" / "out.txt"
    elsewhere = tmp_path / "elsewhere.txt"
    shutil.copy(output, elsewhere)  # the same bytes: the digest alone would pass
    output.unlink()
    os.symlink(elsewhere, output)
    calls.clear()
    assert run_experiment(experiment, root, workers=0).ok
    assert calls == ["group/a"] and not output.is_symlink()
    assert elsewhere.read_text() == "result of group/a"


def test_the_unit_locks_never_follow_a_link(sweep, tmp_path):
    experiment, root, _ = sweep
    root.mkdir(parents=True)
    victim = tmp_path / "victim"
    victim.mkdir()
    os.symlink(victim, root / ".locks")
    assert run_experiment(experiment, root, workers=0).ok
    assert list(victim.iterdir()) == [] and not (root / ".locks").is_symlink()


def test_a_run_lock_planted_as_a_link_is_refused_with_one_line(sweep, tmp_path):
    experiment, root, calls = sweep
    root.mkdir(parents=True)
    target = tmp_path / "somebody_elses.lock"
    os.symlink(target, root / ".lock")
    with pytest.raises(RunnerError, match="symbolic link") as error:
        run_experiment(experiment, root, workers=0)
    assert "\n" not in str(error.value) and not target.exists() and calls == []
    with pytest.raises(UnsafePathError), file_lock(root / ".lock"):
        pass
    assert not target.exists()


@pytest.mark.parametrize("damage", ["deep", "huge", "big integer", "link"])
def test_a_deep_or_huge_marker_is_redone_and_the_sweep_goes_on(sweep, tmp_path, damage):
    experiment, root, calls = sweep
    assert run_experiment(experiment, root, workers=0).ok
    marker = root / "group" / "a" / "done.json"
    good = json.loads(marker.read_text())
    if damage == "deep":
        marker.write_text(json.dumps(good)[:-1] + ', "x": ' + "[" * 100_000 + "]" * 100_000 + "}")
    elif damage == "huge":
        marker.write_text(json.dumps({**good, "padding": "x" * (3 << 20)}))
    elif damage == "big integer":
        marker.write_text(json.dumps(good)[:-1] + ', "x": ' + "7" * 5000 + "}")
    else:
        elsewhere = tmp_path / "done.json"
        shutil.copy(marker, elsewhere)
        marker.unlink()
        os.symlink(elsewhere, marker)
    assert unit_states(root, [Unit("group/a", "fine", {"n": 1})])["group/a"] == "corrupt"
    calls.clear()
    summary = run_experiment(experiment, root, workers=0)
    assert summary.ok and calls == ["group/a"]
    assert json.loads(marker.read_text())["unit"] == "group/a"


def test_a_deep_plan_is_one_line_for_the_report(sweep):
    experiment, root, _ = sweep
    assert run_experiment(experiment, root, workers=0).ok
    (root / "units.json").write_text("[" * 200_000 + "]" * 200_000)
    with pytest.raises(RunnerError, match="nested too deeply") as error:
        read_plan(root)
    assert "\n" not in str(error.value)
    (root / "units.json").write_text(json.dumps([{"id": "../../outside", "kind": "fine", "params": {}}]))
    with pytest.raises(RunnerError, match="outside the run directory"):
        read_plan(root)


def test_bounded_json_reader():
    assert parse_json('{"a": [1, {"b": "]]]]"}]}', "x") == {"a": [1, {"b": "]]]]"}]}
    for text, words in (("[" * 65 + "]" * 65, "nested too deeply"), ("9" * 5000, "not valid JSON"),
                        (b"\xff\xfe{}", "not UTF-8"), ('{"a": ', "not valid JSON")):
        with pytest.raises(UntrustedInputError, match=words) as error:
            parse_json(text, "thing.json")
        assert "\n" not in str(error.value) and "thing.json" in str(error.value)
    with pytest.raises(UntrustedInputError, match="larger than"):
        read_json("/proc/self/maps", max_bytes=16)  # the size check holds where the filesystem reports none
    with pytest.raises(UntrustedInputError, match="is a directory"):
        read_json(REPO)
    # Linear time even for an unterminated string full of escaped quotes (a regex could retry from each quote)
    started = time.perf_counter()
    with pytest.raises(UntrustedInputError):
        parse_json('"' + '\\"' * 400_000, "x")
    assert time.perf_counter() - started < 5


# ---------------------------------------------------------------------------------------------------------------
# Training runs
# ---------------------------------------------------------------------------------------------------------------

def _train_small(out: Path, **kwargs):
    return train(ENV, "odv-ppo", seed=1, timesteps=TOTAL, out_dir=out, n_envs=2, overrides=SMALL, eval_every=128,
                 eval_episodes=1, tensorboard=False, **kwargs)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("finished") / "run"
    _train_small(out)
    return out


@pytest.fixture
def run_copy(finished_run, tmp_path) -> Path:
    """The run as a kill after its last checkpoint leaves it (status running, no model.zip)."""
    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    (out / "model.zip").unlink()
    (out / "run.json").write_text(json.dumps({**json.loads((out / "run.json").read_text()), "status": "running"}))
    return out


def _state(out: Path) -> dict:
    return json.loads((out / "checkpoints" / "state.json").read_text())


def _checkpoint(out: Path) -> Path:
    return out / "checkpoints" / _state(out)["checkpoint"]


def _members(path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def _write_zip(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def test_train_api_refuses_a_directory_holding_a_run_and_force_moves_it_aside(finished_run, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    model = (out / "model.zip").read_bytes()
    with pytest.raises(RunDirectoryExists, match="resume=True") as error:
        _train_small(out)
    assert "force=True" in str(error.value) and (out / "model.zip").read_bytes() == model

    result = _train_small(out, resume=True)  # the same call with resume=True runs again and loses nothing
    assert result.timesteps == TOTAL and (out / "model.zip").read_bytes() == model
    with pytest.raises(ValueError, match="one of them"):
        _train_small(out, resume=True, force=True)

    result = _train_small(out, force=True)
    (old,) = tmp_path.glob("run.old-*")
    assert (old / "model.zip").read_bytes() == model and result.model_path == out / "model.zip"


def test_resume_refuses_a_directory_of_another_run_without_checkpoint(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    recorded = {"env_config": socnav.load_config({"scenario": "circle_crossing"}).model_dump(mode="json"),
                "algo": "ppo", "algo_config": {}, "overrides": {}, "seed": 0, "timesteps": 100, "n_envs": 1,
                "eval_every": 64, "eval_episodes": 1, "status": "running"}
    (out / "run.json").write_text(json.dumps(recorded))
    with pytest.raises(CheckpointError, match="holds another run"):
        _train_small(out, resume=True)
    assert json.loads((out / "run.json").read_text()) == recorded


@pytest.mark.parametrize("planted", ["checkpoints", "tb", "curve.csv", "checkpoints/state.json"])
def test_a_link_inside_a_training_run_is_refused_and_its_target_untouched(run_copy, tmp_path, planted):
    victim = tmp_path / "victim"
    original = run_copy / planted
    if original.is_dir():
        shutil.copytree(original, victim)
    elif original.exists():
        victim.parent.mkdir(exist_ok=True)
        shutil.copy(original, victim)
    else:
        victim.mkdir()
    before = {p: p.read_bytes() for p in ([victim] if victim.is_file() else victim.rglob("*")) if p.is_file()}
    if original.is_dir():
        shutil.rmtree(original)
    else:
        original.unlink(missing_ok=True)
    os.symlink(victim, original)

    with pytest.raises(UnsafePathError, match="symbolic link"):
        _train_small(run_copy, resume=True)
    assert not can_resume(run_copy)  # the experiment runner wipes such a unit instead of continuing it
    result = runner.invoke(app, ["train", "--resume", str(run_copy)])
    _one_line_cli_error(result, "symbolic link", planted.split("/")[0])
    after = {p: p.read_bytes() for p in ([victim] if victim.is_file() else victim.rglob("*")) if p.is_file()}
    assert after == before


def test_moving_a_run_aside_never_follows_its_lock(run_copy, tmp_path):
    target = tmp_path / "not_a_lock.txt"
    target.write_text("somebody's file")
    (run_copy / ".lock").unlink(missing_ok=True)
    os.symlink(target, run_copy / ".lock")
    with pytest.raises(UnsafePathError, match="symbolic link"):
        move_run_aside(run_copy)
    assert target.read_text() == "somebody's file" and run_copy.is_dir()


def test_a_partial_training_unit_with_a_link_inside_is_redone_not_continued(run_copy, tmp_path):
    from socnav.experiments.runner import prepare_unit_dir as _prepare_unit_dir

    root = tmp_path / "sweep"
    unit = Unit("train/x", "train", {"n": 1})
    directory = root / "train" / "x"
    directory.parent.mkdir(parents=True)
    shutil.copytree(run_copy, directory)
    (directory / "unit.json").write_text(json.dumps(unit.to_json()))
    assert can_resume(directory)
    victim = tmp_path / "victim"
    shutil.copytree(directory / "checkpoints", victim)
    shutil.rmtree(directory / "checkpoints")
    os.symlink(victim, directory / "checkpoints")
    before = sorted(p.name for p in victim.iterdir())
    _prepare_unit_dir(root, unit, "partial")
    assert sorted(p.name for p in directory.iterdir()) == ["unit.json"]  # wiped: redone from scratch
    assert sorted(p.name for p in victim.iterdir()) == before


# ---------------------------------------------------------------------------------------------------------------
# Checkpoints and state cross-checked before a run resumes
# ---------------------------------------------------------------------------------------------------------------

def _with_optimizer(checkpoint: Path, edit) -> Path:
    members = _members(checkpoint)
    payload = th.load(io.BytesIO(members["state.pt"]), weights_only=True)
    edit(payload["optimizer"])
    buffer = io.BytesIO()
    th.save(payload, buffer)
    members["state.pt"] = buffer.getvalue()
    return _write_zip(checkpoint, members)


def _group(key, value):
    def edit(optimizer):
        optimizer["param_groups"][0][key] = value
    return edit


def _slot(key, value):
    def edit(optimizer):
        slot = optimizer["state"][0]
        slot[key] = value(slot[key]) if callable(value) else value
    return edit


OPTIMIZER_EDITS = {
    "maximize": (_group("maximize", True), "maximize"),
    "weight_decay": (_group("weight_decay", 10.0), "weight_decay"),
    "learning rate": (_group("lr", 50.0), "lr"),
    "betas of the wrong type": (_group("betas", ("0.9", 0.999)), "betas"),
    "eps zero": (_group("eps", 0.0), "eps"),
    "amsgrad switched on": (_group("amsgrad", True), "amsgrad"),
    "unknown setting": (_group("nesterov", True), "nesterov"),
    "step tensor of many values": (_slot("step", lambda step: th.zeros(10_000)), "step"),
    "negative step": (_slot("step", lambda step: th.tensor(-3.0)), "step"),
    "negative second moment": (_slot("exp_avg_sq", lambda value: -value - 1), "negative"),
    "moment of another dtype": (_slot("exp_avg", lambda value: value.double()), "dtype"),
    "sparse moment": (_slot("exp_avg", lambda value: value.to_sparse()), "sparse"),
    "extra slot": (_slot("momentum_buffer", th.zeros(1)), "momentum_buffer"),
}


@pytest.mark.parametrize("case", list(OPTIMIZER_EDITS))
def test_crafted_optimizer_settings_are_refused_before_training_resumes(run_copy, case):
    edit, word = OPTIMIZER_EDITS[case]
    checkpoint = _with_optimizer(_checkpoint(run_copy), edit)
    with pytest.raises(CheckpointError, match=word) as error:
        load_checkpoint(checkpoint, socnav.make_vec_env(ENV, n_envs=2))
    assert "\n" not in str(error.value)
    assert not can_resume(run_copy)  # a sweep redoes such a unit instead of failing on it at every rerun
    result = runner.invoke(app, ["train", "--resume", str(run_copy)])
    _one_line_cli_error(result, "--resume", word)


def test_checkpoint_schedule_must_be_its_own_hyperparameter(run_copy):
    checkpoint = _checkpoint(run_copy)
    members = _members(checkpoint)
    header = json.loads(members["checkpoint.json"])
    header["learning_rate"] = {"kind": "constant", "value": 0.9}  # algo_config says 2.5e-4
    members["checkpoint.json"] = json.dumps(header).encode()
    _write_zip(checkpoint, members)
    with pytest.raises(CheckpointError, match="learning_rate"):
        load_checkpoint(checkpoint, socnav.make_vec_env(ENV, n_envs=2))


@pytest.mark.parametrize("field, change", [("curve_rows", -1), ("eval_rows", -1), ("next_eval", 128),
                                           ("wall_time_s", 100.0)])
def test_state_counters_must_match_the_checkpoint_and_logs_are_never_truncated(run_copy, field, change):
    state_file = run_copy / "checkpoints" / "state.json"
    state_file.write_text(json.dumps({**_state(run_copy), field: _state(run_copy)[field] + change}))
    logs = {name: (run_copy / name).read_bytes() for name in ("curve.csv", "eval.csv")}
    result = runner.invoke(app, ["train", "--resume", str(run_copy)])
    _one_line_cli_error(result, "--resume", field)
    assert {name: (run_copy / name).read_bytes() for name in logs} == logs
    assert not can_resume(run_copy)


def test_logs_that_do_not_continue_the_checkpoint_are_refused(run_copy):
    curve = pd.read_csv(run_copy / "curve.csv")
    curve.loc[len(curve) - 1, "timesteps"] = 64  # the checkpoint's last row, moved to an earlier step
    curve.to_csv(run_copy / "curve.csv", index=False)
    result = runner.invoke(app, ["train", "--resume", str(run_copy)])
    _one_line_cli_error(result, "--resume", "curve.csv", "step")
    assert pd.read_csv(run_copy / "curve.csv")["timesteps"].tolist()[-1] == 64  # left as it was


def test_rows_a_killed_run_logged_past_its_checkpoint_are_redone(run_copy):
    # A kill between writing the logs of a new checkpoint and its state.json: the logs hold later rows.
    curve = pd.read_csv(run_copy / "curve.csv")
    later = curve.iloc[[-1]].assign(timesteps=TOTAL + 128)
    pd.concat([curve, later]).to_csv(run_copy / "curve.csv", index=False)
    assert can_resume(run_copy)
    result = _train_small(run_copy, resume=True)
    assert result.timesteps == TOTAL
    assert pd.read_csv(run_copy / "curve.csv")["timesteps"].tolist() == [128, 256]


# ---------------------------------------------------------------------------------------------------------------
# Policy files: tensors and zip archives
# ---------------------------------------------------------------------------------------------------------------

def _policy_with(tmp_path: Path, name: str, edit) -> Path:
    members = _members(pretrained_path())
    state = th.load(io.BytesIO(members["policy.pt"]), weights_only=True)
    edit(state)
    buffer = io.BytesIO()
    th.save(state, buffer)
    members["policy.pt"] = buffer.getvalue()
    return _write_zip(tmp_path / name, members)


@pytest.mark.parametrize("kind, word", [("sparse", "sparse"), ("meta", "meta"), ("float64", "float64")])
def test_sparse_meta_and_other_dtype_tensors_are_a_policy_load_error(tmp_path, kind, word):
    def edit(state):
        weight = state["action_net.weight"]
        state["action_net.weight"] = {"sparse": weight.to_sparse(), "meta": th.empty(weight.shape, device="meta"),
                                      "float64": weight.double()}[kind]

    with pytest.raises(PolicyLoadError, match=word) as error:
        load_policy(_policy_with(tmp_path, f"{kind}.zip", edit))
    assert "\n" not in str(error.value)


def _end_record(data: bytes) -> int:
    return data.rindex(b"PK\x05\x06")


@pytest.mark.parametrize("craft, words", [
    (lambda data, at: struct.pack_into("<HH", data, at + 8, 60_000, 60_000), "60000 entries"),
    (lambda data, at: struct.pack_into("<I", data, at + 12, 50 << 20), "central directory"),
    (lambda data, at: struct.pack_into("<HH", data, at + 8, 0xFFFF, 0xFFFF), "zip64"),
])
def test_zip_member_count_is_read_from_the_end_record_before_zipfile_parses(tmp_path, monkeypatch, craft, words):
    data = bytearray(pretrained_path().read_bytes())
    craft(data, _end_record(data))
    path = tmp_path / "crafted.zip"
    path.write_bytes(bytes(data))
    opened = []
    real = zipfile.ZipFile
    monkeypatch.setattr(zipfile, "ZipFile", lambda *a, **k: opened.append(a) or real(*a, **k))
    with pytest.raises(PolicyLoadError, match=words):
        load_policy(path)
    assert opened == []  # refused before zipfile built an entry per central-directory record


def test_zip_with_too_many_entries_is_refused_before_parsing(tmp_path, monkeypatch):
    path = tmp_path / "many.zip"
    with zipfile.ZipFile(path, "w") as archive:
        for name in ("socnav.json", "policy.pt", *(f"pad{i}" for i in range(40))):
            archive.writestr(name, b"")
    monkeypatch.setattr(zipfile, "ZipFile", lambda *a, **k: pytest.fail("zipfile parsed the archive"))
    with pytest.raises(PolicyLoadError, match="42 entries"):
        load_policy(path)


def test_the_shipped_policy_still_loads():
    assert load_policy("pretrained").socnav_metadata["algo"] == "odv-ppo-drop"
