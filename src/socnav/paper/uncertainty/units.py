"""Units of the `uncertainty` experiment kind: the perturbation study (Table 2), threshold calibration and the safety
evaluation (Table 3, its rule ablation and trade-off curve). Each executor reads the trained policies of its
dependencies and writes Parquet records."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from socnav.envs.perturbations import PERTURBATIONS, perturbed_config, strength_zero
from socnav.envs.rollout import rollout_episodes
from socnav.experiments.registry import (
    ExecutorResult,
    UnitProgress,
    file_digest,
    json_safe,
    register_executor,
    single_threaded_torch,
    unit_dir,
)
from socnav.experiments.spec import Unit
from socnav.io import write_table_atomic, write_text_atomic
from socnav.paper.uncertainty.plan import NO_ESTIMATOR, calibration_unit_id, tradeoff_thresholds_file
from socnav.uncertainty import MC_SEED


def _policies(root: Path, unit: Unit) -> tuple[list[Any], dict[str, dict[str, Any]]]:
    """The trained policies of the unit's training dependencies (the acting one first) and their digests."""
    from socnav.rl.persistence import load_policy

    trains = [dep for dep in unit.deps if dep.startswith("train/")]
    paths = [unit_dir(root, dep) / "model.zip" for dep in trains]
    inputs = {f"{dep}/model.zip": file_digest(path) for dep, path in zip(trains, paths, strict=True)}
    return [load_policy(path) for path in paths], inputs


def build_estimator(kind: str, policies: list[Any], k: int, p_test: float | None = None) -> Any:
    """The uncertainty estimator of a unit: MC-dropout on the acting policy (`k` samples, seeded with `MC_SEED`,
    dropout `p_test` when given) or the ensemble of every policy."""
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
    bar = UnitProgress(directory, len(p["strengths"]) * p["episodes"], "episodes")
    for strength in p["strengths"]:
        config = perturbed_config(p["env"], p["perturbation"], strength)
        # a fresh, seeded estimator per strength: the dropout masks do not depend on which strengths ran before
        estimator = build_estimator(p["estimator"], policies, p["k"], p["p_test"])
        steps, episodes = record_uncertainty(policies[0], estimator, config, p["episodes"], seed=p["seed"],
                                             n_envs=p["n_envs"], window=p["window"], progress=bar.advance)
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
    """Calibration records on perturbations and seeds disjoint from the evaluation, then `calibrate`: thresholds for
    the unit's budget (``thresholds.yaml``, ``calibration.json``) and, with ``tradeoff_budgets``, for each of those
    on the same episodes (``thresholds-budget<b>.yaml``, ``calibration-budget<b>.json``). A ``proximity-only``
    rule reads no uncertainty: no estimator is built for it."""
    from socnav.safety import calibrate_budgets, save_thresholds

    p = unit.params
    single_threaded_torch()
    policies, inputs = _policies(root, unit)
    conditions = p.get("conditions", "paper")
    estimator = None if conditions == "proximity-only" else build_estimator(p["estimator"], policies, p["k"])
    budgets = [p["budget"], *p.get("tradeoff_budgets", [])]
    light = p.get("tradeoff_budgets", []) if p.get("tradeoff_search") == "light" else []
    results = calibrate_budgets(policies[0], estimator, p["env"], p["episodes"], budgets, p["proximity"],
                                p["window"], sensing=p["sensing"], conditions=conditions, light=light,
                                progress=UnitProgress(directory, 1, "replays").update)
    files = []
    for budget, (thresholds, report) in results.items():
        if conditions != "paper":  # the directory does not name the estimator of an ablated rule
            report = {**report, "estimator": p["estimator"] if p["estimator"] is not None else NO_ESTIMATOR}
        names = (("thresholds.yaml", "calibration.json") if budget == p["budget"] else
                 (tradeoff_thresholds_file(budget), f"calibration-budget{budget:g}.json"))
        save_thresholds(thresholds, directory / names[0])
        write_text_atomic(directory / names[1], json.dumps(json_safe(report), indent=2))
        files += list(names)
    return ExecutorResult(files, inputs=inputs)


#: Per-episode columns the safety units add with an ablation (`socnav.safety.FallbackCounter.columns`).
ABLATION_COLUMNS = ("proximity_steps", "vetoed_steps", "fallback_digest")


@dataclass(frozen=True)
class SafetyVariant:
    """One safe variant of a safety unit: the record tags and the thresholds it plays."""

    name: str  # none / paper (the paper's thresholds) / calibrated
    thresholds: Any
    rule: str = "paper"  # Thresholds.conditions
    budget: float = math.nan  # the false-activation budget a calibrated rule was chosen for (NaN: not calibrated)
    repeats: int | None = None  # played in the first this many repeats only (a trade-off budget); None: all


def _calibrated(root: Path, unit: Unit, inputs: dict[str, dict[str, Any]], calibration: str, file: str,
                sensing: str) -> Any:
    """Thresholds a calibration dependency wrote to `file`, with `sensing` (its digest recorded in `inputs`)."""
    from socnav.safety import Thresholds, load_thresholds

    path = unit_dir(root, calibration) / file
    inputs[f"{calibration}/{file}"] = file_digest(path)
    return Thresholds.create(load_thresholds(path).model_dump(), sensing=sensing)


def play_safety_episodes(p: dict[str, Any], policy: Any, variants: list[SafetyVariant],
                         make_estimator: Callable[[Any], Any], tags: dict[str, Any], ablation: bool,
                         unperturbed: bool = True, progress: UnitProgress | None = None) -> pd.DataFrame:
    """The plain policy and every variant on the same episodes, at every strength and repeat (the records of
    `_execute_safety`); with `ablation` also the ``rule`` and ``budget`` tags and :data:`ABLATION_COLUMNS`, and the
    unperturbed strength only if ``unperturbed`` is true (the same world and episodes in every safety unit);
    `progress` counts the (strength, repeat) settings played."""
    from socnav.safety import FallbackCounter, SafePolicy

    parts = []
    kind = p["perturbation"]
    for strength in p["strengths"]:
        if ablation and not unperturbed and kind in PERTURBATIONS and math.isclose(strength, strength_zero(kind)):
            continue  # played by the unit of the first perturbation type
        config = perturbed_config(p["env"], kind, strength)
        for repeat in range(p["repeats"]):
            seed = p["seed"] + repeat * p["episodes"]
            block = {**tags, "perturbation": p["perturbation"], "strength": float(strength), "repeat": repeat}
            plain = rollout_episodes(policy, config, p["episodes"], seed=seed, n_envs=p["n_envs"])
            plain["fallback_steps"] = 0
            extra = {"rule": "", "budget": math.nan} if ablation else {}
            if ablation:
                plain = plain.assign(proximity_steps=0, vetoed_steps=0, fallback_digest="")
            parts.append(_tag(plain, **block, variant="none", sensing="", **extra))
            played: dict[Any, pd.DataFrame] = {}
            for variant in variants:
                if variant.repeats is not None and repeat >= variant.repeats:
                    continue
                thresholds = variant.thresholds
                # Without observation noise the true state IS the observation: both sensings play the same
                # episodes, so a rollout already played with the other sensing is reused.
                key = (thresholds.model_copy(update={"sensing": "perceived"})
                       if config.perturbation.observation_noise == 0.0 else thresholds)
                if key not in played:
                    # a fresh, seeded estimator per run: every variant sees the same dropout masks
                    safe = SafePolicy(policy, make_estimator(thresholds), thresholds, config, window=p["window"])
                    counter = FallbackCounter(safe)
                    records = rollout_episodes(safe, config, p["episodes"], seed=seed, n_envs=p["n_envs"],
                                               observer=counter)
                    columns = counter.columns(records["episode"])
                    for name in ("fallback_steps", *(ABLATION_COLUMNS if ablation else ())):
                        records[name] = columns[name]
                    played[key] = records
                extra = {"rule": variant.rule, "budget": variant.budget} if ablation else {}
                parts.append(_tag(played[key].copy(), **block, variant=variant.name, sensing=thresholds.sensing,
                                  **extra))
            if progress is not None:
                progress.advance()
    return pd.concat(parts, ignore_index=True)


def _settings(p: dict[str, Any], unperturbed: bool = True) -> int:
    """The (strength, repeat) settings `play_safety_episodes` plays for the unit parameters `p`."""
    kind = p["perturbation"]
    skipped = (not unperturbed and kind in PERTURBATIONS
               and any(math.isclose(strength, strength_zero(kind)) for strength in p["strengths"]))
    return max(1, (len(p["strengths"]) - skipped) * p["repeats"])


@register_executor("safety_eval")
def _execute_safety(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    """The same episodes without the safety layer and with each threshold set and sensing, at every strength and
    repeat. Records: ``variant`` (none / paper / calibrated) and ``sensing`` (perceived / true; empty for none).
    With ``ablation`` (`socnav.experiments.spec.Safety.ablation`): for its sensing also the uncertainty-only rule
    and the paper's rule at the trade-off budgets, and the columns ``rule`` (``Thresholds.conditions``; empty for
    none), ``budget`` (the calibration's false-activation budget; NaN for none and the paper's thresholds) and
    :data:`ABLATION_COLUMNS`; the unperturbed strength (the same episodes in every unit) is then played by the unit
    of the first perturbation type only (``ablation.unperturbed``)."""
    from socnav.safety import Thresholds, load_thresholds

    p = unit.params
    single_threaded_torch()
    policies, inputs = _policies(root, unit)
    ablation = p.get("ablation")
    main_budget = ablation["budget"] if ablation else math.nan
    # The paper's threshold sets take the experiment's proximity reading; calibrated ones keep the variant chosen.
    paper = Thresholds.create(load_thresholds(p["thresholds"]).model_dump(), proximity=p["proximity"])
    variants: list[SafetyVariant] = []
    for sensing in p["sensing"]:
        variants.append(SafetyVariant("paper", Thresholds.create(paper.model_dump(), sensing=sensing)))
        calibration = calibration_unit_id(p["estimator"], sensing)
        if calibration in unit.deps:
            thresholds = _calibrated(root, unit, inputs, calibration, "thresholds.yaml", sensing)
            variants.append(SafetyVariant("calibrated", thresholds, budget=main_budget))
    if ablation:
        sensing = ablation["sensing"]
        for budget in ablation["tradeoff_budgets"]:
            thresholds = _calibrated(root, unit, inputs, calibration_unit_id(p["estimator"], sensing),
                                     tradeoff_thresholds_file(budget), sensing)
            variants.append(SafetyVariant("calibrated", thresholds, budget=budget,
                                          repeats=ablation.get("tradeoff_repeats")))
        for rule in ablation["rules"]:
            calibration = calibration_unit_id(p["estimator"], sensing, rule)
            thresholds = _calibrated(root, unit, inputs, calibration, "thresholds.yaml", sensing)
            variants.append(SafetyVariant("calibrated", thresholds, rule=rule, budget=main_budget))
    unperturbed = ablation.get("unperturbed", True) if ablation else True
    records = play_safety_episodes(p, policies[0], variants,
                                   lambda _: build_estimator(p["estimator"], policies, p["k"]),
                                   {"estimator": p["estimator"]}, ablation=bool(ablation), unperturbed=unperturbed,
                                   progress=UnitProgress(directory, _settings(p, unperturbed), "settings"))
    write_table_atomic(records, directory / "episodes.parquet")
    return ExecutorResult(["episodes.parquet"], inputs=inputs)


@register_executor("safety_eval_proximity")
def _execute_safety_proximity(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    """The safety unit of the proximity-only rule (no estimator: it reads no uncertainty): the plain policy and the
    rule calibrated at each of ``budgets`` (the first: the main budget), on the episodes of every other safety unit
    (the unperturbed strength only with ``unperturbed``). Records as `_execute_safety`'s with an ablation,
    ``estimator`` = ``none``."""
    p = unit.params
    single_threaded_torch()
    policies, inputs = _policies(root, unit)
    calibration = calibration_unit_id(NO_ESTIMATOR, p["sensing"], "proximity-only")
    variants = [SafetyVariant("calibrated",
                              _calibrated(root, unit, inputs, calibration,
                                          "thresholds.yaml" if index == 0 else tradeoff_thresholds_file(b),
                                          p["sensing"]),
                              rule="proximity-only", budget=b,
                              repeats=None if index == 0 else p.get("tradeoff_repeats"))
                for index, b in enumerate(p["budgets"])]
    from socnav.safety import no_uncertainty

    # nothing estimated; a calibration that found no rule within its budget wrote thresholds that never fire (an
    # uncertainty rule with infinite thresholds), which read the zero uncertainty
    records = play_safety_episodes(p, policies[0], variants, lambda t: no_uncertainty if t.uses_uncertainty else None,
                                   {"estimator": NO_ESTIMATOR}, ablation=True, unperturbed=p["unperturbed"],
                                   progress=UnitProgress(directory, _settings(p, p["unperturbed"]), "settings"))
    write_table_atomic(records, directory / "episodes.parquet")
    return ExecutorResult(["episodes.parquet"], inputs=inputs)
