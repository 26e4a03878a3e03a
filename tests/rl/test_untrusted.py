"""Untrusted run directories and model files: nothing in a checkpoint, a run directory or a policy file executes
code, an existing run is never destroyed, and every crafted input gets a clear one-line error naming what is wrong."""

from __future__ import annotations

import base64
import io
import json
import pickle
import resource
import shutil
import struct
import zipfile
from pathlib import Path

import pandas as pd
import pytest
import torch as th
from typer.testing import CliRunner

import socnav
from socnav.cli import app
from socnav.io import file_lock
from socnav.rl import make_model
from socnav.rl.persistence import (
    CheckpointError,
    PolicyLoadError,
    load_checkpoint,
    load_policy,
    save_checkpoint,
    save_policy,
)
from socnav.rl.training import RunDirectoryBusy, train

ENV = {"scenario": "position_swap", "n_humans": 1}
SMALL = {"n_steps": 64, "batch_size": 64, "n_epochs": 2}
TOTAL = 256
runner = CliRunner()


class Payload:
    """Unpickling this creates the file `marker`: planted in a checkpoint, it shows whether code ran."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (exec, (f"open({str(self.marker)!r}, 'w').close()",))


def _train_small(out: Path, timesteps: int = TOTAL, resume: bool = False):
    return train(ENV, "odv-ppo", seed=1, timesteps=timesteps, out_dir=out, n_envs=2, overrides=SMALL,
                 eval_every=128, eval_episodes=1, resume=resume, tensorboard=False)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A complete tiny training run (checkpoints at 128 and 256 steps); tests work on copies."""
    out = tmp_path_factory.mktemp("finished") / "run"
    _train_small(out)
    return out


@pytest.fixture
def run_copy(finished_run, tmp_path) -> Path:
    """A copy of the run as a kill after its last checkpoint leaves it: status running, no model.zip yet."""
    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    (out / "model.zip").unlink()
    (out / "run.json").write_text(json.dumps({**json.loads((out / "run.json").read_text()), "status": "running"}))
    return out


def _state(out: Path) -> dict:
    return json.loads((out / "checkpoints" / "state.json").read_text())


def _checkpoint(out: Path) -> Path:
    return out / "checkpoints" / _state(out)["checkpoint"]


def _sb3_zip_with_pickled_schedule(path: Path, marker: Path, num_timesteps: int) -> Path:
    """SB3's own checkpoint format (what socnav wrote before) with a pickle in place of ``lr_schedule``."""
    model = make_model("odv-ppo", socnav.make_vec_env(ENV, n_envs=2), seed=0, overrides=SMALL)
    model.num_timesteps = num_timesteps
    model.save(path)
    with zipfile.ZipFile(path) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(members["data"])
    data["lr_schedule"] = {":type:": "<class 'function'>",
                           ":serialized:": base64.b64encode(pickle.dumps(Payload(marker))).decode()}
    members["data"] = json.dumps(data).encode()
    _write_zip(path, members)
    return path


def _write_zip(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def _members(path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def _one_line_cli_error(result, *words: str) -> None:
    """Exit code 2 with the error's words in the output (rich may wrap lines: compared with whitespace joined)."""
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit) and "Traceback" not in result.output, result.output
    output = " ".join(result.output.split())
    for word in words:
        assert word in output, (word, result.output)


# ---------------------------------------------------------------------------------------------------------------
# 1. Safe checkpoints
# ---------------------------------------------------------------------------------------------------------------

def test_checkpoint_is_tensors_and_json_and_round_trips_bit_identically(finished_run, tmp_path):
    checkpoint = _checkpoint(finished_run)
    assert set(_members(checkpoint)) == {"checkpoint.json", "state.pt"}  # no SB3 pickles ("data", "*.pth")
    header = json.loads(_members(checkpoint)["checkpoint.json"])
    assert header["num_timesteps"] == TOTAL == _state(finished_run)["num_timesteps"]
    assert header["learning_rate"] == {"kind": "constant", "value": 2.5e-4}  # the odv-ppo preset's, as data
    assert header["n_updates"] == (TOTAL // 128) * SMALL["n_epochs"]

    model, loaded = load_checkpoint(checkpoint, socnav.make_vec_env(ENV, n_envs=2))
    assert model.num_timesteps == TOTAL and model._n_updates == header["n_updates"]
    assert model.lr_schedule(0.3) == 2.5e-4 and model.policy.optimizer.state_dict()["state"]  # Adam moments restored
    assert th.isfinite(model.policy.feature_range[0]).all()  # the tracked feature range came back
    again = save_checkpoint(model, tmp_path / "again.zip", loaded.env_config, loaded.seed, loaded.run)
    assert again.read_bytes() == checkpoint.read_bytes()


@pytest.mark.parametrize("plant", ["sb3-pickled-lr-schedule", "serialized-schedule-in-header", "pickle-in-state"])
def test_planted_pickle_in_a_checkpoint_is_refused_on_resume_with_nothing_executed(run_copy, tmp_path, plant):
    marker = tmp_path / "pwned"
    checkpoint = _checkpoint(run_copy)
    if plant == "sb3-pickled-lr-schedule":
        _sb3_zip_with_pickled_schedule(checkpoint, marker, TOTAL)
    else:
        members = _members(checkpoint)
        if plant == "serialized-schedule-in-header":
            header = json.loads(members["checkpoint.json"])
            header["learning_rate"] = {":type:": "<class 'function'>",
                                       ":serialized:": base64.b64encode(pickle.dumps(Payload(marker))).decode()}
            members["checkpoint.json"] = json.dumps(header).encode()
        else:
            buffer = io.BytesIO()
            th.save({"policy": Payload(marker), "optimizer": {}}, buffer)
            members["state.pt"] = buffer.getvalue()
        _write_zip(checkpoint, members)
    before = checkpoint.read_bytes()

    result = runner.invoke(app, ["train", "--resume", str(run_copy)])
    _one_line_cli_error(result, "--resume")
    assert not marker.exists(), "code planted in the checkpoint ran"
    assert checkpoint.read_bytes() == before  # refused, not deleted or overwritten


def test_rerun_of_a_sweep_never_executes_a_planted_checkpoint(tmp_path):
    from socnav.experiments.registry import unit_dir
    from socnav.experiments.runner import execute_unit
    from socnav.experiments.spec import Unit

    params = {"env": ENV, "algo": "odv-ppo", "seed": 0, "timesteps": TOTAL, "n_envs": 2, "overrides": SMALL,
              "eval_every": 128, "validation_episodes": 1}
    unit, root = Unit("train/position_swap/odv-ppo/seed0", "train", params), tmp_path / "sweep"
    assert execute_unit(unit.to_json(), str(root))["status"] == "done"
    directory = unit_dir(root, unit)
    (directory / "done.json").unlink()  # as if killed after its last checkpoint: the rerun resumes the unit
    marker = tmp_path / "pwned"
    _sb3_zip_with_pickled_schedule(_checkpoint(directory), marker, TOTAL)

    outcome = execute_unit(unit.to_json(), str(root))
    assert not marker.exists(), "code planted in the checkpoint ran"
    assert outcome["status"] == "done", outcome
    assert json.loads((directory / "done.json").read_text())["resumed"] is False  # wiped and trained afresh
    assert list(pd.read_csv(directory / "curve.csv")["timesteps"]) == [128, 256]


@pytest.mark.parametrize("name", ["../../x.zip", "/tmp/x.zip", "sub/step_256.zip", "..", "step_256.zip/"])
def test_state_json_checkpoint_must_be_a_plain_name_inside_checkpoints(run_copy, name):
    outside = (run_copy / "checkpoints" / name).resolve() if not name.startswith("/") else None
    if outside is not None and name.endswith(".zip"):  # a valid checkpoint where the name points: never followed
        outside.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(_checkpoint(run_copy), outside)
    state_file = run_copy / "checkpoints" / "state.json"
    state_file.write_text(json.dumps({**_state(run_copy), "checkpoint": name}))
    result = runner.invoke(app, ["train", "--resume", str(run_copy)])
    _one_line_cli_error(result, "checkpoint", "step_<N>.zip")


def test_checkpoint_of_another_run_is_refused_before_it_is_built(run_copy):
    run_file = run_copy / "run.json"
    run_file.write_text(json.dumps({**json.loads(run_file.read_text()), "overrides": {**SMALL, "n_epochs": 3}}))
    result = runner.invoke(app, ["train", "--resume", str(run_copy)])
    _one_line_cli_error(result, "belongs to another run", "algo_config")


# ---------------------------------------------------------------------------------------------------------------
# 2. train --out: never destroy a run, one writer at a time
# ---------------------------------------------------------------------------------------------------------------

TINY = ["--scenario", "position_swap", "--n-humans", "1", "--algo", "odv-ppo", "--timesteps", "128", "--n-envs",
        "2", "--eval-episodes", "1", "--set", "n_steps=64", "--set", "batch_size=64", "--set", "n_epochs=1"]


def test_train_refuses_an_existing_directory_and_force_moves_it_aside(tmp_path):
    out = tmp_path / "mine"
    (out / "checkpoints").mkdir(parents=True)
    (out / "checkpoints" / "important.zip").write_bytes(b"precious")
    result = runner.invoke(app, ["train", *TINY, "--out", str(out)])
    _one_line_cli_error(result, "already holds files", "--resume", "--force")
    assert (out / "checkpoints" / "important.zip").read_bytes() == b"precious"
    assert sorted(p.name for p in out.rglob("*")) == ["checkpoints", "important.zip"]  # nothing written

    result = runner.invoke(app, ["train", *TINY, "--out", str(out), "--force"])
    assert result.exit_code == 0, result.output
    (old,) = tmp_path.glob("mine.old-*")
    assert (old / "checkpoints" / "important.zip").read_bytes() == b"precious"
    assert (out / "model.zip").is_file() and not (out / "checkpoints" / "important.zip").exists()


def test_train_out_naming_a_file_is_a_clear_error(tmp_path):
    out = tmp_path / "file.txt"
    out.write_text("not a directory")
    result = runner.invoke(app, ["train", *TINY, "--out", str(out)])
    _one_line_cli_error(result, "is an existing file")
    assert out.read_text() == "not a directory"


def test_a_second_training_in_the_same_directory_is_refused(run_copy):
    with file_lock(run_copy / ".lock", blocking=False) as locked:  # as a running `socnav train` holds it
        assert locked
        with pytest.raises(RunDirectoryBusy, match="another socnav train"):
            _train_small(run_copy, resume=True)
        result = runner.invoke(app, ["train", "--resume", str(run_copy)])
        _one_line_cli_error(result, "another socnav train")
        result = runner.invoke(app, ["train", *TINY, "--out", str(run_copy), "--force"])
        _one_line_cli_error(result, "another socnav train")  # --force never moves a live run aside
    assert (run_copy / "run.json").is_file() and not list(run_copy.parent.glob("run.old-*"))


def test_deleted_state_json_recovers_from_the_checkpoint_never_restarts_over_it(run_copy, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(run_copy, broken)
    (run_copy / "checkpoints" / "state.json").unlink()
    result = _train_small(run_copy, timesteps=2 * TOTAL, resume=True)  # continue the run to a larger total
    assert result.resumed_from == TOTAL and result.timesteps == 2 * TOTAL
    assert list(pd.read_csv(run_copy / "curve.csv")["timesteps"]) == [128, 256, 384, 512]

    (broken / "checkpoints" / "state.json").unlink()
    (broken / "curve.csv").unlink()  # the logs the checkpoint continues are gone: it cannot resume consistently
    checkpoint = next((broken / "checkpoints").glob("step_*.zip"))
    result = runner.invoke(app, ["train", "--resume", str(broken)])
    _one_line_cli_error(result, "state.json", "is missing", "move")
    assert checkpoint.is_file()  # refused, never deleted


# ---------------------------------------------------------------------------------------------------------------
# 3. Temporary files of a killed writer
# ---------------------------------------------------------------------------------------------------------------

def test_temporaries_of_a_killed_training_are_removed_on_the_next_start(run_copy):
    stale = [run_copy / "checkpoints" / ".state.json.k2j3h4g5.tmp.json", run_copy / ".model.zip.ab_cd123.tmp.zip",
             run_copy / "checkpoints" / ".step_512.zip.q9w8e7r6.tmp.zip", run_copy / ".curve.csv.zzzzzzzz.tmp.csv"]
    kept = [run_copy / ".notes", run_copy / "draft.abcdefgh.tmp.txt"]  # not atomic_path's names
    for path in stale + kept:
        path.write_bytes(b"half-written")
    _train_small(run_copy, resume=True)
    assert not any(path.exists() for path in stale)
    assert all(path.exists() for path in kept)


def test_temporaries_of_a_killed_sweep_are_removed_on_the_next_run(tmp_path, monkeypatch):
    import yaml

    from socnav.experiments.registry import EXECUTORS, ExecutorResult
    from socnav.experiments.runner import run_experiment
    from socnav.experiments.spec import PLANNERS, Unit, load_experiment

    def fine(root, unit, directory) -> ExecutorResult:
        (directory / "out.txt").write_text("ok")
        return ExecutorResult(["out.txt"])

    monkeypatch.setitem(PLANNERS, "temp-demo", lambda experiment: [Unit("demo/a", "fine", {"n": 1})])
    monkeypatch.setitem(EXECUTORS, "fine", fine)
    smoke = Path(__file__).resolve().parents[2] / "configs" / "experiments" / "smoke.yaml"
    spec = {**yaml.safe_load(smoke.read_text()), "kind": "temp-demo", "budgets": {}}
    (tmp_path / "demo.yaml").write_text(yaml.safe_dump(spec))
    experiment, root = load_experiment(tmp_path / "demo.yaml"), tmp_path / "run"
    assert run_experiment(experiment, root, workers=0).ok
    (root / "demo" / "a" / "done.json").unlink()  # killed while redoing the unit
    stale = [root / ".units.json.abcdefgh.tmp.json", root / "demo" / "a" / ".out.txt.k2j3h4g5.tmp.txt"]
    for path in stale:
        path.write_bytes(b"half-written")
    assert run_experiment(experiment, root, workers=0).ok
    assert not any(path.exists() for path in stale)


# ---------------------------------------------------------------------------------------------------------------
# 8. Crafted policy files: always a one-line PolicyLoadError
# ---------------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def policy_file(tmp_path_factory) -> Path:
    model = make_model("odv-ppo-drop", socnav.make_vec_env(ENV, n_envs=1), seed=1)
    model.policy.features_extractor.update_feature_range(th.randn(5, 64))
    metadata = {"algo": "odv-ppo-drop", "algo_config": model.algo_config, "seed": 1, "timesteps": 0,
                "env_config": socnav.load_config(ENV).model_dump(mode="json")}
    return save_policy(model.policy, tmp_path_factory.mktemp("policy") / "policy.zip", metadata)


def _with_header(source: Path, target: Path, **changes) -> Path:
    members = _members(source)
    header = json.loads(members["socnav.json"])
    members["socnav.json"] = json.dumps({**header, **changes}).encode()
    return _write_zip(target, members)


def _with_algo_config(source: Path, target: Path, **changes) -> Path:
    header = json.loads(_members(source)["socnav.json"])
    return _with_header(source, target, algo_config={**header["algo_config"], **changes})


def _with_weights(source: Path, target: Path, edit) -> Path:
    members = _members(source)
    state = th.load(io.BytesIO(members["policy.pt"]), weights_only=True)
    edit(state)
    buffer = io.BytesIO()
    th.save(state, buffer)
    members["policy.pt"] = buffer.getvalue()
    return _write_zip(target, members)


def _patch_headers(source: Path, target: Path, field: str, value: int, member: str | None = None) -> Path:
    """Set a field of every entry's (or `member`'s) local header and central-directory record, as a hex editor
    would: the general purpose ``flags``, the compression ``method`` or the uncompressed ``size`` (zipfile's writer
    would not write such values)."""
    local, central, layout = {"flags": (6, 8, "<H"), "method": (8, 10, "<H"), "size": (22, 24, "<I")}[field]
    data = bytearray(source.read_bytes())
    with zipfile.ZipFile(source) as archive:
        offsets = [info.header_offset for info in archive.infolist() if member in (None, info.filename)]
        position = archive.start_dir
    for offset in offsets:
        struct.pack_into(layout, data, offset + local, value)
    while data[position:position + 4] == b"PK\x01\x02":
        name, extra, comment = struct.unpack_from("<HHH", data, position + 28)
        if member in (None, data[position + 46:position + 46 + name].decode()):
            struct.pack_into(layout, data, position + central, value)
        position += 46 + name + extra + comment
    target.write_bytes(bytes(data))
    return target


def _bomb(source: Path, target: Path, member: str, size: int) -> Path:
    with zipfile.ZipFile(source) as archive, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as bomb:
        for name in archive.namelist():
            if name != member:
                bomb.writestr(name, archive.read(name))
        with bomb.open(member, "w") as stream:
            zeros = bytes(1 << 20)
            for _ in range(size >> 20):
                stream.write(zeros)
    return target


def _set(key: str, index: tuple, value: float):
    def edit(state):
        state[key][index] = value
    return edit


CRAFTED = {
    "encrypted flag": (lambda s, t: _patch_headers(s, t, "flags", 0x1), "encrypted"),
    "compression method 99": (lambda s, t: _patch_headers(s, t, "method", 99), "compression method 99"),
    "deeply nested header": (lambda s, t: _write_zip(t, {**_members(s), "socnav.json": b"[" * 10**5 + b"]" * 10**5}),
                             "nested too deeply"),
    "huge lstm": (lambda s, t: _with_algo_config(s, t, lstm_hidden_size=10**9), "lstm_hidden_size"),
    "huge layers": (lambda s, t: _with_algo_config(s, t, net_arch_pi=[1 << 40, 1 << 40]), "net_arch_pi"),
    "many layers": (lambda s, t: _with_algo_config(s, t, n_lstm_layers=10**6), "n_lstm_layers"),
    "large net, small weights": (lambda s, t: _with_algo_config(s, t, lstm_hidden_size=4096, net_arch_pi=[4096] * 8),
                                 "do not fit"),
    "weights bomb": (lambda s, t: _bomb(s, t, "policy.pt", 300 << 20), "over the limit"),
    "header bomb": (lambda s, t: _bomb(s, t, "socnav.json", 8 << 20), "over the limit"),
    "bomb declaring a small size": (lambda s, t: _patch_headers(_bomb(s, t.with_suffix(".big"), "policy.pt", 300 << 20),
                                                                t, "size", 1000, "policy.pt"), "corrupted"),
    "NaN weight": (lambda s, t: _with_weights(s, t, _set("action_net.weight", (0, 0), float("nan"))), "NaN or Inf"),
    "Inf weight": (lambda s, t: _with_weights(s, t, _set("value_net.bias", (0,), float("inf"))), "NaN or Inf"),
    "Inf feature range": (lambda s, t: _with_weights(s, t, _set("features_extractor.h_max", (3,), float("inf"))),
                          "NaN or Inf"),
    "unknown algo": (lambda s, t: _with_header(s, t, algo="nope"), "algo"),
    "seed not a number": (lambda s, t: _with_header(s, t, seed="zero"), "seed"),
    "negative timesteps": (lambda s, t: _with_header(s, t, timesteps=-5), "timesteps"),
    "unknown header field": (lambda s, t: _with_header(s, t, loader="os.system"), "loader"),
    "header not an object": (lambda s, t: _write_zip(t, {**_members(s), "socnav.json": b"[1, 2]"}), "format"),
}


@pytest.mark.parametrize("case", list(CRAFTED))
def test_crafted_policy_file_gives_a_one_line_policy_load_error(policy_file, tmp_path, case):
    craft, words = CRAFTED[case]
    path = craft(policy_file, tmp_path / "crafted.zip")
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(PolicyLoadError) as error:
        load_policy(path)
    assert words in str(error.value) and "\n" not in str(error.value), str(error.value)
    grown_mib = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before) / 1024
    assert grown_mib < 150, f"reading the file took {grown_mib:.0f} MiB"  # sizes checked before allocating


def test_untouched_policy_file_still_loads(policy_file):
    policy = load_policy(policy_file)
    assert policy.socnav_metadata["algo"] == "odv-ppo-drop" and not policy.training


def test_crafted_checkpoint_is_a_checkpoint_error(run_copy, tmp_path):
    checkpoint = _checkpoint(run_copy)
    members = _members(checkpoint)
    header = json.loads(members["checkpoint.json"])
    for changes, word in (({"algo": "nope"}, "algo"), ({"num_timesteps": "256"}, "num_timesteps"),
                          ({"algo_config": {**header["algo_config"], "lstm_hidden_size": 10**9}}, "lstm_hidden_size")):
        _write_zip(tmp_path / "bad.zip", {**members, "checkpoint.json": json.dumps({**header, **changes}).encode()})
        with pytest.raises(CheckpointError, match=word) as error:
            load_checkpoint(tmp_path / "bad.zip", socnav.make_vec_env(ENV, n_envs=2))
        assert "\n" not in str(error.value)


# ---------------------------------------------------------------------------------------------------------------
# 9. Tampered run metadata
# ---------------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("file, field, value", [
    ("checkpoints/state.json", "curve_rows", "12"),
    ("checkpoints/state.json", "num_timesteps", -1),
    ("checkpoints/state.json", "wall_time_s", "soon"),
    ("run.json", "timesteps", "lots"),
    ("run.json", "timesteps", -5),
    ("run.json", "algo", "nope"),
    ("run.json", "seed", 2**40),
    ("run.json", "n_envs", 0),
])
def test_tampered_run_metadata_names_the_field(run_copy, file, field, value):
    path = run_copy / file
    path.write_text(json.dumps({**json.loads(path.read_text()), field: value}))
    result = runner.invoke(app, ["train", "--resume", str(run_copy)])
    _one_line_cli_error(result, field)
