"""Units of the `uncertainty` experiment kind: the perturbation study (Table 2), threshold calibration and the safety
evaluation (Table 3). Each executor reads the trained policies of its dependencies and writes Parquet records.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd

from socnav.envs.perturbations import perturbed_config
from socnav.envs.rollout import rollout_episodes
from socnav.experiments.registry import (
    ExecutorResult, file_digest, json_safe, register_executor, single_threaded_torch, unit_dir,
)
from socnav.experiments.spec import Unit, calibration_unit_id
from socnav.io import write_table_atomic, write_text_atomic
from socnav.uncertainty import MC_SEED


def _policies(root: Path, unit: Unit) -> tuple[list[Any], dict[str, dict[str, Any]]]:
    """The trained policies of the unit's training dependencies (the acting one first) and their digests."""
    from socnav.rl.persistence import load_policy

    trains = [dep for dep in unit.deps if dep.startswith("train/")]
    paths = [unit_dir(root, dep) / "model.zip" for dep in trains]
    inputs = {f"{dep}/model.zip": file_digest(path) for dep, path in zip(trains, paths)}
    return [load_policy(path) for path in paths], inputs


def _estimator(kind: str, policies: list[Any], k: int, p_test: float | None = None) -> Any:
    from socnav.uncertainty import EnsembleEstimator, MCDropoutEstimator

    if kind == "mc":
        return MCDropoutEstimator(policies[0], k=k, p_test=p_test, seed=MC_SEED)
    return EnsembleEstimator(policies)


def _tag(frame: pd.DataFrame, **columns: Any) -> pd.DataFrame:
    for position, (name, value) in enumerate(columns.items()):
        frame.insert(position, name, value)
    return frame


@register_executor("uncertainty_study")
def _execute_study(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    from socnav.uncertainty.recording import record_uncertainty

    p = unit.params
    single_threaded_torch()
    policies, inputs = _policies(root, unit)
    steps_parts, episode_parts, summary = [], [], {}
    for strength in p["strengths"]:
        config = perturbed_config(p["env"], p["perturbation"], strength)
        # a fresh, seeded estimator per strength: the dropout masks do not depend on which strengths ran before
        estimator = _estimator(p["estimator"], policies, p["k"], p["p_test"])
        steps, episodes = record_uncertainty(policies[0], estimator, config, p["episodes"], seed=p["seed"],
                                             n_envs=p["n_envs"], window=p["window"])
        tags = {"estimator": p["estimator"], "perturbation": p["perturbation"], "strength": float(strength)}
        steps_parts.append(_tag(steps, **tags))
        episode_parts.append(_tag(episodes, **tags))
        summary[str(strength)] = {"collision_pct": 100.0 * float((episodes["outcome"] == "collision").mean()),
                                  **{name: float(steps[name].mean()) for name in
                                     ("u_ep_heading", "u_ep_speed", "u_al_heading", "u_al_speed", "u_feat")}}
    write_table_atomic(pd.concat(steps_parts, ignore_index=True), directory / "steps.parquet")
    write_table_atomic(pd.concat(episode_parts, ignore_index=True), directory / "episodes.parquet")
    write_text_atomic(directory / "summary.json", json.dumps(json_safe(summary), indent=2))
    return ExecutorResult(["steps.parquet", "episodes.parquet", "summary.json"], inputs=inputs)


@register_executor("calibrate")
def _execute_calibrate(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    """Calibration records on perturbations and seeds disjoint from the evaluation, then `calibrate`."""
    from socnav.safety import calibrate_thresholds, save_thresholds

    p = unit.params
    single_threaded_torch()
    policies, inputs = _policies(root, unit)
    thresholds, report = calibrate_thresholds(policies[0], _estimator(p["estimator"], policies, p["k"]), p["env"],
                                              p["episodes"], p["budget"], p["proximity"], p["window"],
                                              sensing=p["sensing"])
    save_thresholds(thresholds, directory / "thresholds.yaml")
    write_text_atomic(directory / "calibration.json", json.dumps(json_safe(report), indent=2))
    return ExecutorResult(["thresholds.yaml", "calibration.json"], inputs=inputs)


@register_executor("safety_eval")
def _execute_safety(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    """The same episodes without the safety layer and with each threshold set and sensing, at every strength and
    repeat. Records: ``variant`` (none / paper / calibrated) and ``sensing`` (perceived / true; empty for none)."""
    from socnav.safety import FallbackCounter, SafePolicy, Thresholds, load_thresholds

    p = unit.params
    single_threaded_torch()
    policies, inputs = _policies(root, unit)
    # The paper's threshold sets take the experiment's proximity reading; calibrated ones keep the variant chosen.
    paper = Thresholds.create(load_thresholds(p["thresholds"]).model_dump(), proximity=p["proximity"])
    variants: list[tuple[str, Any]] = []
    for sensing in p["sensing"]:
        variants.append(("paper", Thresholds.create(paper.model_dump(), sensing=sensing)))
        calibration = calibration_unit_id(p["estimator"], sensing)
        if calibration in unit.deps:
            path = unit_dir(root, calibration) / "thresholds.yaml"
            variants.append(("calibrated", Thresholds.create(load_thresholds(path).model_dump(), sensing=sensing)))
            inputs[f"{calibration}/thresholds.yaml"] = file_digest(path)
    parts = []
    for strength in p["strengths"]:
        config = perturbed_config(p["env"], p["perturbation"], strength)
        for repeat in range(p["repeats"]):
            seed = p["seed"] + repeat * p["episodes"]
            tags = {"estimator": p["estimator"], "perturbation": p["perturbation"], "strength": float(strength),
                    "repeat": repeat}
            plain = rollout_episodes(policies[0], config, p["episodes"], seed=seed, n_envs=p["n_envs"])
            plain["fallback_steps"] = 0
            parts.append(_tag(plain, **tags, variant="none", sensing=""))
            played: dict[Any, pd.DataFrame] = {}
            for name, thresholds in variants:
                # Without observation noise the true state IS the observation: both sensings play the same
                # episodes, so a rollout already played with the other sensing is reused.
                key = (thresholds.model_copy(update={"sensing": "perceived"})
                       if config.perturbation.observation_noise == 0.0 else thresholds)
                if key not in played:
                    # a fresh, seeded estimator per run: every variant sees the same dropout masks
                    estimator = _estimator(p["estimator"], policies, p["k"])
                    safe = SafePolicy(policies[0], estimator, thresholds, config, window=p["window"])
                    counter = FallbackCounter(safe)
                    records = rollout_episodes(safe, config, p["episodes"], seed=seed, n_envs=p["n_envs"],
                                               observer=counter)
                    records["fallback_steps"] = counter.per_episode(records["episode"])
                    played[key] = records
                parts.append(_tag(played[key].copy(), **tags, variant=name, sensing=thresholds.sensing))
    write_table_atomic(pd.concat(parts, ignore_index=True), directory / "episodes.parquet")
    return ExecutorResult(["episodes.parquet"], inputs=inputs)
