"""The Ray backend as users run it: `socnav run --backend ray --address ADDR` against a
multi-node Ray cluster on this machine (every node on 127.0.0.1), one node killed while it runs a unit. The sweep
finishes with every unit done exactly once and results identical to the local backend's."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml

# A plain import, not importorskip: Ray is in the `test` extra, so a missing Ray fails this module.
from ray.cluster_utils import Cluster

from socnav.experiments.registry import unit_dir
from socnav.experiments.runner import read_plan, run_experiment, unit_state
from socnav.experiments.spec import load_experiment, plan_units

pytestmark = pytest.mark.heavy  # a multi-node Ray cluster in subprocesses, one node killed

EPISODES = 48  # long enough that a unit is still running when its node is killed, even on a loaded machine
EXPERIMENT = {
    "name": "cluster",
    "env": {"n_humans": 2},
    "grid": {"algorithms": ["ppo"], "train_scenarios": ["circle_crossing"], "seeds": [0, 1], "timesteps": 256,
             "n_envs": 2, "eval_every": 256, "validation_episodes": 2,
             "overrides": {"n_steps": 64, "batch_size": 64, "n_epochs": 1}},
    # one environment at a time: each evaluation takes a few seconds, so a node dies while it runs one
    "evaluation": {"scenarios": ["circle_crossing", "random"], "episodes": EPISODES, "seed": 0, "n_envs": 1},
}


@pytest.fixture
def cluster():
    """A head node (no CPUs: it hosts the driver, never a unit) and two 1-CPU worker nodes, all on 127.0.0.1."""
    # Short (Ray's socket paths must fit in 108 bytes) and private: Ray writes the cluster's address under
    # RAY_TMPDIR, where `ray.init()` of other processes on this machine would otherwise find it.
    temp_dir = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    previous = os.environ.get("RAY_TMPDIR")
    os.environ["RAY_TMPDIR"] = temp_dir
    loopback = {"node_ip_address": "127.0.0.1", "object_store_memory": 80 * 2**20}
    head = {**loopback, "num_cpus": 0, "include_dashboard": False,
            # a killed node is noticed within ~1 s (Ray's defaults take up to ~30 s)
            "_system_config": {"health_check_initial_delay_ms": 0, "health_check_period_ms": 500,
                               "health_check_failure_threshold": 2}}
    nodes = Cluster(initialize_head=True, head_node_args=head)
    try:
        workers = [nodes.add_node(num_cpus=1, **loopback) for _ in range(2)]
        yield nodes, workers, temp_dir
    finally:
        nodes.shutdown()
        if previous is None:
            os.environ.pop("RAY_TMPDIR", None)
        else:
            os.environ["RAY_TMPDIR"] = previous
        shutil.rmtree(temp_dir, ignore_errors=True)


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _running_evals(root: Path, eval_ids: list[str]) -> list[str]:
    """Evaluation units that have started (unit.json written) and not finished (no done.json)."""
    return [unit for unit in eval_ids
            if (unit_dir(root, unit) / "unit.json").exists() and not (unit_dir(root, unit) / "done.json").exists()]


def test_cli_sweep_on_a_multi_node_cluster_survives_a_killed_node(tmp_path, cluster):
    nodes, workers, temp_dir = cluster
    spec = tmp_path / "cluster.yaml"
    spec.write_text(yaml.safe_dump(EXPERIMENT))
    units = [unit.id for unit in plan_units(load_experiment(spec))]
    eval_ids = [unit for unit in units if unit.startswith("eval/")]
    assert len(units) == 6 and len(eval_ids) == 4

    # RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0: Ray keeps 127.0.0.1 as given instead of replacing it by this machine's
    # network address, where a loopback-only cluster does not listen (see docs/reproduction.md, "On a Ray cluster").
    env = {**os.environ, "RAY_TMPDIR": temp_dir, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    ray_root = tmp_path / "ray"
    command = [sys.executable, "-m", "socnav.cli", "run", str(spec), "--backend", "ray", "--address", nodes.address,
               "--out", str(ray_root)]
    sweep = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        # generous: on a fresh install every Ray worker compiles the numba kernels before its first unit
        deadline = time.monotonic() + 400
        while sweep.poll() is None and len(_running_evals(ray_root, eval_ids)) < 2:
            assert time.monotonic() < deadline, "the sweep never ran two evaluations at once"
            time.sleep(0.05)
        # both 1-CPU workers are busy with an evaluation: killing either loses a running unit
        interrupted = _running_evals(ray_root, eval_ids)
        assert len(interrupted) == 2, "the sweep ended before a node could be killed"
        nodes.remove_node(workers[0], allow_graceful=False)  # SIGKILL: a crashed machine, not a drained one
        output, _ = sweep.communicate(timeout=400)
    finally:
        if sweep.poll() is None:
            sweep.kill()
    assert sweep.returncode == 0, output
    assert "6 done, 0 already done, 0 failed" in output, output

    # every unit done exactly once: sound markers, no errors, each test episode recorded once
    _, plan = read_plan(ray_root)
    assert sorted(unit.id for unit in plan) == sorted(units)
    for unit in plan:
        assert unit_state(ray_root, unit) == "done", unit.id
        assert not (unit_dir(ray_root, unit) / "error.txt").exists()
    previous = {unit: json.loads((unit_dir(ray_root, unit) / "done.json").read_text())["previous_state"]
                for unit in units}
    redone = [unit for unit, state in previous.items() if state == "partial"]
    assert len(redone) == 1 and redone[0] in interrupted, previous  # the killed node's unit, retried elsewhere
    assert all(state == "pending" for unit, state in previous.items() if unit not in redone), previous
    for unit in eval_ids:
        episodes = pd.read_parquet(unit_dir(ray_root, unit) / "episodes.parquet")["episode"]
        assert sorted(episodes) == list(range(EPISODES)), unit

    # the same experiment on the local backend gives the same models and the same evaluation records
    local_root = tmp_path / "local"
    summary = run_experiment(load_experiment(spec), local_root, backend="local", workers=0)
    assert summary.ok and summary.count("done") == 6
    for unit in units:
        if unit.startswith("train/"):
            assert _digest(unit_dir(ray_root, unit) / "model.zip") == _digest(unit_dir(local_root, unit) / "model.zip")
        else:
            pd.testing.assert_frame_equal(pd.read_parquet(unit_dir(ray_root, unit) / "episodes.parquet"),
                                          pd.read_parquet(unit_dir(local_root, unit) / "episodes.parquet"))
            assert (json.loads((unit_dir(ray_root, unit) / "summary.json").read_text())
                    == json.loads((unit_dir(local_root, unit) / "summary.json").read_text()))
