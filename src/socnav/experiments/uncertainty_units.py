"""Units of the `uncertainty` experiment kind: the perturbation study (Table 2), threshold calibration and the safety
evaluation (Table 3). Each executor reads the trained policies of its dependencies and writes Parquet records.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

import pandas as pd

from socnav.config import load_config
from socnav.envs.rollout import rollout_episodes
from socnav.experiments.perturbations import CALIBRATION_SEED, CALIBRATION_SET, perturbed_config
from socnav.experiments.runner import ExecutorResult, _json_safe, _single_threaded_torch, file_digest, register_executor, unit_dir
from socnav.experiments.spec import Unit, calibration_unit_id
from socnav.io import write_table_atomic, write_text_atomic

#: Seed of the MC-dropout masks: the study is reproducible run to run.
MC_SEED = 0


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


def _perturbed(env: dict[str, Any], perturbation: str, strength: float) -> Any:
    return perturbed_config(env, perturbation, strength)


def _tag(frame: pd.DataFrame, **columns: Any) -> pd.DataFrame:
    for position, (name, value) in enumerate(columns.items()):
        frame.insert(position, name, value)
    return frame


@register_executor("uncertainty_study")
def _execute_study(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    from socnav.uncertainty.recording import record_uncertainty

    p = unit.params
    _single_threaded_torch()
    policies, inputs = _policies(root, unit)
    steps_parts, episode_parts, summary = [], [], {}
    for strength in p["strengths"]:
        config = _perturbed(p["env"], p["perturbation"], strength)
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
    write_text_atomic(directory / "summary.json", json.dumps(_json_safe(summary), indent=2))
    return ExecutorResult(["steps.parquet", "episodes.parquet", "summary.json"], inputs=inputs)


#: Leads searched by the calibration proxy: the rule must fire at least this many steps before the collision step.
CALIBRATION_LEADS = (0, 1, 2)
#: The proxy search also runs at these fractions of the budget: candidates with a margin below it.
PROXY_BUDGET_SHARES = (1.0, 0.5)


def calibrate_thresholds(policy: Any, estimator: Any, env: dict[str, Any], episodes: int, budget: float = 0.05,
                         proximity: str = "both", window: int = 4, confidence: float = 0.95,
                         progress: Callable[[int, int], None] | None = None,
                         sensing: str = "perceived") -> tuple[Any, dict[str, Any]]:
    """Thresholds chosen on calibration episodes: `episodes` unperturbed ones and `episodes` per strength of
    `CALIBRATION_SET`, from episode seeds `CALIBRATION_SEED`... (disjoint from the evaluation's).

    Two stages. (1) The proxy search (`socnav.safety.calibrate`) on per-step records of the plain policy proposes
    one candidate per proximity variant (`proximity`: one of `PROXIMITY_VARIANTS`, or `both`), lead in
    `CALIBRATION_LEADS` and proxy budget (`PROXY_BUDGET_SHARES` of `budget`): the proxy alone rewards a rule that
    fires at the very step of the contact, too late for the fallback when humans close fast, so candidates that
    must fire 1 or 2 steps earlier compete too. (2) `socnav.safety.select_by_rollouts` replays the same
    calibration episodes with each candidate's `SafePolicy` and keeps the one that prevents the most collisions
    (the worst perturbation type, then the mean over types) among those whose false-activation rate is within
    `budget` at `confidence` (one-sided upper bound), both MEASURED in those rollouts. Both stages score per
    perturbation type, worst type first (`socnav.safety.calibration`): no type is traded for another.

    `progress(done, total)`: episodes played so far and in all (the total shrinks once the number of distinct
    candidates is known; it starts at the most there can be).

    `sensing` (``perceived`` | ``true``, `socnav.safety.Thresholds.sensing`): what the rule's proximity terms and
    the fallback read, in the records and the replays alike; the thresholds returned carry it.

    :return: ``(thresholds, report)``; without any collision to learn from, thresholds that never fire.
    """
    from socnav.safety import (PROXIMITY_VARIANTS, CalibrationRun, Thresholds, calibrate, collect_records,
                               select_by_rollouts)

    if proximity != "both" and proximity not in PROXIMITY_VARIANTS:
        raise ValueError(f"proximity must be one of: both, {', '.join(PROXIMITY_VARIANTS)}; got {proximity!r}")
    variants = PROXIMITY_VARIANTS if proximity == "both" else (proximity,)
    configs = [("unperturbed", load_config(env))]
    configs += [(kind, _perturbed(env, kind, strength)) for kind, strengths in CALIBRATION_SET.items()
                for strength in strengths]
    n_envs = min(episodes, 40)
    runs = [CalibrationRun(config, kind != "unperturbed", episodes, CALIBRATION_SEED + index * episodes, kind)
            for index, (kind, config) in enumerate(configs)]
    per_pass = episodes * len(runs)
    most_candidates = len(PROXY_BUDGET_SHARES) * len(variants) * len(CALIBRATION_LEADS)
    played = {"done": 0, "total": per_pass * (2 + most_candidates)}  # collection, plain replay, candidates

    def advance(n: int) -> None:
        played["done"] += n
        if progress is not None:
            progress(played["done"], played["total"])

    parts = [collect_records(policy, estimator, run.config, episodes, seed=run.seed, perturbed=run.perturbed,
                             window=window, n_envs=n_envs, episode_offset=index * episodes, progress=advance,
                             sensing=sensing).assign(group=run.group)
             for index, run in enumerate(runs)]
    records = pd.concat(parts, ignore_index=True)
    common = {"calibration_set": CALIBRATION_SET, "calibration_seed": CALIBRATION_SEED,
              "false_activation_budget": budget, "episodes_per_configuration": episodes,
              "proximity_searched": list(variants), "leads_searched": list(CALIBRATION_LEADS),
              "proxy_budgets": [share * budget for share in PROXY_BUDGET_SHARES], "confidence": confidence,
              "sensing": sensing}
    if not records.loc[records["perturbed"], "collided"].any():
        # Nothing to learn from: the layer could only cost false activations, so it is switched off.
        thresholds = Thresholds.create(Thresholds.never().model_dump(), sensing=sensing)
        return thresholds, {"thresholds": thresholds.model_dump(), "prevented_fraction": float("nan"),
                            "false_activation_rate": 0.0, "n_collisions": 0,
                            "note": "no collision in the calibration episodes: thresholds that never fire", **common}
    candidates, proxies = [], []
    for share in PROXY_BUDGET_SHARES:
        for variant in variants:
            for lead in CALIBRATION_LEADS:
                result = calibrate(records, false_activation_budget=share * budget, proximity=variant, lead=lead)
                candidate = Thresholds.create(result.thresholds.model_dump(), sensing=sensing)
                if candidate not in candidates:
                    candidates.append(candidate)
                    proxies.append({"lead": lead, "proxy_budget": share * budget,
                                    "proxy_prevented_fraction": result.prevented_fraction,
                                    "proxy_worst_type_fraction": result.worst_type_fraction,
                                    "proxy_false_activation_rate": result.false_activation_rate})
    played["total"] = per_pass * (2 + len(candidates))
    thresholds, table = select_by_rollouts(candidates, policy, estimator, runs, budget, window, n_envs, confidence,
                                           progress=advance)
    thresholds = Thresholds.create(thresholds.model_dump(), sensing=sensing)  # also when none met the budget
    table = pd.concat([table, pd.DataFrame(proxies)], axis=1)
    chosen = table[table["chosen"]]
    report = {"thresholds": thresholds.model_dump(), "n_collisions": int(table["plain_collisions"].iloc[0]),
              "prevented_fraction": float(chosen["prevented_fraction"].iloc[0]) if len(chosen) else 0.0,
              "prevented_worst": float(chosen["prevented_worst"].iloc[0]) if len(chosen) else 0.0,
              "false_activation_rate": float(chosen["false_activation_rate"].iloc[0]) if len(chosen) else 0.0,
              "false_activation_upper": float(chosen["false_activation_upper"].iloc[0]) if len(chosen) else 0.0,
              "candidates": table.to_dict(orient="records"), **common}
    if not len(chosen):
        report["note"] = ("no candidate met the false-activation budget in the calibration rollouts (at the "
                          f"{confidence:.0%} upper bound): thresholds that never fire")
    return thresholds, report


@register_executor("calibrate")
def _execute_calibrate(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    """Calibration records on perturbations and seeds disjoint from the evaluation, then `calibrate`."""
    from socnav.safety import save_thresholds

    p = unit.params
    _single_threaded_torch()
    policies, inputs = _policies(root, unit)
    thresholds, report = calibrate_thresholds(policies[0], _estimator(p["estimator"], policies, p["k"]), p["env"],
                                              p["episodes"], p["budget"], p["proximity"], p["window"],
                                              sensing=p["sensing"])
    save_thresholds(thresholds, directory / "thresholds.yaml")
    write_text_atomic(directory / "calibration.json", json.dumps(_json_safe(report), indent=2))
    return ExecutorResult(["thresholds.yaml", "calibration.json"], inputs=inputs)


@register_executor("safety_eval")
def _execute_safety(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    """The same episodes without the safety layer and with each threshold set and sensing, at every strength and
    repeat. Records: ``variant`` (none / paper / calibrated) and ``sensing`` (perceived / true; empty for none)."""
    from socnav.safety import FallbackCounter, SafePolicy, Thresholds, load_thresholds

    p = unit.params
    _single_threaded_torch()
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
        config = _perturbed(p["env"], p["perturbation"], strength)
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
