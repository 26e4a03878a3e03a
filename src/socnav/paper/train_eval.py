"""The units every kind of the paper's experiments starts with: train one policy (algorithm, scenario, seed) and
evaluate a trained policy on test episodes -- their ids, their planning and their executors.
"""

from __future__ import annotations

import json
from pathlib import Path

from socnav.experiments.registry import (
    ExecutorResult,
    UnitProgress,
    file_digest,
    json_safe,
    register_executor,
    single_threaded_torch,
    unit_dir,
)
from socnav.experiments.spec import Experiment
from socnav.experiments.units import Unit
from socnav.io import write_text_atomic

__all__ = ["eval_unit_id", "train_unit", "train_unit_id"]


def train_unit_id(scenario: str, algo: str, seed: int) -> str:
    return f"train/{scenario}/{algo}/seed{seed}"


def eval_unit_id(train_scenario: str, algo: str, seed: int, eval_scenario: str) -> str:
    return f"eval/{train_scenario}/{algo}/seed{seed}/{eval_scenario}"


def train_unit(experiment: Experiment, scenario: str, algo: str, seed: int) -> Unit:
    grid = experiment.grid
    return Unit(train_unit_id(scenario, algo, seed), "train", {
        "train_scenario": scenario, "algo": algo, "seed": seed, "timesteps": grid.timesteps,
        "env": experiment.env_config(scenario), "overrides": experiment.algo_overrides(algo),
        "n_envs": grid.n_envs, "eval_every": grid.eval_every, "validation_episodes": grid.validation_episodes,
    })


def _sound_checkpoint(directory: Path) -> bool:
    """Whether `train(resume=True)` can continue the training unit in `directory` (or start it: no checkpoint yet):
    its state.json and the checkpoint it names validate and agree (read safely, nothing unpickled)."""
    from socnav.rl.training import can_resume

    return can_resume(directory)


@register_executor("train", resumable=_sound_checkpoint)
def _execute_train(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    from socnav.rl.training import train

    p = unit.params
    single_threaded_torch()
    bar = UnitProgress(directory, p["timesteps"], "steps")
    # resume=True: a kept partial unit passed _sound_checkpoint, so train continues from its checkpoint (or starts
    # afresh when there is none) and never discards one.
    result = train(p["env"], p["algo"], p["seed"], p["timesteps"], directory, n_envs=p["n_envs"],
                   overrides=p["overrides"], eval_every=p["eval_every"], eval_episodes=p["validation_episodes"],
                   resume=True, progress=lambda steps, _: bar.update(steps), tensorboard=True)
    return ExecutorResult(["model.zip", "curve.csv", "eval.csv", "run.json"],
                          extra={"timesteps": result.timesteps, "train_wall_time_s": result.wall_time_s,
                                 "resumed": result.resumed_from > 0, "final_validation": result.final_eval})


@register_executor("eval")
def _execute_eval(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    from socnav.envs.rollout import rollout_episodes, summarize
    from socnav.io import write_table_atomic
    from socnav.rl.persistence import load_policy

    p = unit.params
    single_threaded_torch()
    (train_id,) = unit.deps
    model = unit_dir(root, train_id) / "model.zip"
    model_digest = file_digest(model)
    bar = UnitProgress(directory, p["episodes"], "episodes")
    records = rollout_episodes(load_policy(model), p["env"], p["episodes"], seed=p["seed"], n_envs=p["n_envs"],
                               deterministic=p["deterministic"], progress=bar.advance)
    summary = summarize(records)
    records.insert(0, "eval_scenario", p["eval_scenario"])
    records.insert(0, "train_seed", p["train_seed"])
    records.insert(0, "algo", p["algo"])
    records.insert(0, "train_scenario", p["train_scenario"])
    write_table_atomic(records, directory / "episodes.parquet")
    write_text_atomic(directory / "summary.json", json.dumps(json_safe(summary), indent=2, sort_keys=True))
    return ExecutorResult(["episodes.parquet", "summary.json"], inputs={f"{train_id}/model.zip": model_digest})
