"""The planner of the perturbation study and the safety layer's evaluation (kind ``uncertainty``, paper Tables 2
and 3): the ensemble's training units, then study, calibration and safety units -- and their ids.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from socnav.experiments.registry import register_planner
from socnav.experiments.spec import Experiment, ExperimentError, Safety
from socnav.experiments.units import Unit
from socnav.paper.train_eval import train_unit, train_unit_id

__all__ = ["NO_ESTIMATOR", "calibration_unit_id", "plan_uncertainty", "tradeoff_thresholds_file"]

NO_ESTIMATOR = "none"


def calibration_unit_id(estimator: str, sensing: str, conditions: str = "paper") -> str:
    """The calibration unit of an estimator, sensing and rule variant (``perceived`` and the paper's rule add
    nothing to the id, so a run planned without those choices finds its units): ``calibrate[-<sensing>]/<estimator>``,
    ``.../<estimator>-uncertainty-only`` and, for the one rule that reads no uncertainty, ``.../proximity-only``
    (whatever `estimator`)."""
    name = {"paper": estimator, "uncertainty-only": f"{estimator}-uncertainty-only",
            "proximity-only": "proximity-only"}[conditions]
    return f"calibrate/{name}" if sensing == "perceived" else f"calibrate-{sensing}/{name}"


def tradeoff_thresholds_file(budget: float) -> str:
    """The file a calibration unit writes the thresholds of a trade-off budget to (``thresholds.yaml``: its main
    budget)."""
    return f"thresholds-budget{budget:g}.yaml"


def count_uncertainty(experiment: Experiment) -> int:
    """An upper bound of the units `plan_uncertainty` builds, from the grid's sizes alone (nothing expanded)."""
    grid = experiment.grid
    count = len(grid.train_scenarios) * len(grid.algorithms) * len(grid.seeds)  # type: ignore[arg-type]
    if experiment.study is not None:
        count += len(experiment.study.estimators) * len(experiment.study.perturbations)
    if experiment.safety is not None:
        safety = experiment.safety
        rules = (len(safety.estimators) + 1) * (1 + len(safety.ablation))
        count += rules * (len(safety.sensing) + len(safety.perturbations))
    return count


@register_planner("uncertainty", count=count_uncertainty)
def plan_uncertainty(experiment: Experiment) -> list[Unit]:
    """Train the policies of `grid` (one scenario, one algorithm: the ensemble members), then one study unit per
    (estimator, perturbation) and, with `safety`, one calibration unit per estimator and sensing and one safety unit
    per (estimator, perturbation). With `safety.ablation`: an uncertainty-only calibration per estimator (its rows
    played in that estimator's safety units) and one proximity-only calibration, played by its own safety units
    ``safety/none/<perturbation>`` (the rule reads no uncertainty); with `safety.tradeoff_budgets` the calibrations
    of `safety.ablation_sensing` (paper's rule and proximity-only) also choose thresholds at those budgets, played
    by the same safety units."""
    grid, evaluation = experiment.grid, experiment.evaluation
    if len(grid.train_scenarios) != 1 or len(grid.algorithms) != 1:
        raise ExperimentError(f"experiment {experiment.name!r}: kind uncertainty trains one algorithm on one "
                              "scenario (grid.algorithms and grid.train_scenarios must each name one)")
    scenario, algo = grid.train_scenarios[0], grid.algorithms[0]
    trains = [train_unit(experiment, scenario, algo, seed) for seed in grid.seeds]  # type: ignore[union-attr]
    members = tuple(unit.id for unit in trains)
    units = list(trains)
    common = {"env": experiment.env_config(scenario), "episodes": evaluation.episodes, "seed": evaluation.seed,
              "n_envs": evaluation.n_envs}

    def policies(estimator: str, mc_seed: int) -> tuple[str, ...]:
        acting = train_unit_id(scenario, algo, mc_seed)
        if acting not in members:
            raise ExperimentError(f"experiment {experiment.name!r}: mc_seed {mc_seed} is not among grid.seeds")
        return (acting,) if estimator == "mc" else (acting, *[m for m in members if m != acting])

    if experiment.study is not None:
        study = experiment.study
        for estimator in study.estimators:
            for perturbation, strengths in study.perturbations.items():
                units.append(Unit(f"study/{estimator}/{perturbation}", "uncertainty_study", {
                    **common, "estimator": estimator, "perturbation": perturbation, "strengths": strengths,
                    "k": study.k, "p_test": study.p_test, "window": study.window,
                }, deps=policies(estimator, study.mc_seed)))
    if experiment.safety is not None:
        units += _plan_safety(experiment, experiment.safety, common, policies)
    return units


def _plan_safety(experiment: Experiment, safety: Safety, common: dict[str, Any],
                 policies: Callable[[str, int], tuple[str, ...]]) -> list[Unit]:
    """The calibration and safety units of `plan_uncertainty` (its docstring). Without `ablation` and
    `tradeoff_budgets` the units and their parameters are those of the paper's rule alone (same ids and spec
    hashes, so such runs keep their finished units)."""
    units: list[Unit] = []
    ablation_sensing = safety.ablation_sensing_resolved
    extra_budgets = [b for b in safety.tradeoff_budgets if b != safety.false_activation_budget]
    ablated = bool(safety.ablation or safety.tradeoff_budgets)

    def calibration_params(sensing: str, conditions: str = "paper") -> dict[str, Any]:
        params = {"env": common["env"], "episodes": safety.calibration_episodes,
                  "budget": safety.false_activation_budget, "proximity": safety.calibration_proximity,
                  "window": safety.window, "sensing": sensing}
        if sensing == ablation_sensing and extra_budgets and conditions != "uncertainty-only":
            params["tradeoff_budgets"] = extra_budgets
            if safety.tradeoff_search != "full":
                params["tradeoff_search"] = safety.tradeoff_search
        if conditions != "paper":
            params["conditions"] = conditions
        return params

    acting = policies("mc", safety.mc_seed)
    evaluations: list[Unit] = []  # planned after every calibration (see `_relative_cost`)
    proximity_calibration: Unit | None = None
    # Every perturbation type's unperturbed strength is the same world, so its episodes are the same in every
    # safety unit: with the ablation they are played once, by the unit of the first perturbation type.
    first = next(iter(safety.perturbations), None)
    if "proximity-only" in safety.ablation:
        # reads no uncertainty: one calibration (and one evaluation) for all estimators, on the acting policy only
        proximity_calibration = Unit(calibration_unit_id(NO_ESTIMATOR, ablation_sensing, "proximity-only"),
                                     "calibrate", {**calibration_params(ablation_sensing, "proximity-only"),
                                                   "estimator": None}, deps=acting)
        units.append(proximity_calibration)
    for estimator in safety.estimators:
        deps = policies(estimator, safety.mc_seed)
        calibrations: tuple[str, ...] = ()
        if safety.calibrate:
            for sensing in safety.sensing:
                calibration = Unit(calibration_unit_id(estimator, sensing), "calibrate",
                                   {**calibration_params(sensing), "estimator": estimator, "k": safety.k}, deps=deps)
                units.append(calibration)
                calibrations += (calibration.id,)
            if "uncertainty-only" in safety.ablation:
                calibration = Unit(calibration_unit_id(estimator, ablation_sensing, "uncertainty-only"), "calibrate",
                                   {**calibration_params(ablation_sensing, "uncertainty-only"),
                                    "estimator": estimator, "k": safety.k}, deps=deps)
                units.append(calibration)
                calibrations += (calibration.id,)
        for perturbation, strengths in safety.perturbations.items():
            params = {**common, "estimator": estimator, "perturbation": perturbation, "strengths": strengths,
                      "repeats": safety.repeats, "thresholds": safety.thresholds.get(estimator, estimator),
                      "proximity": safety.proximity, "k": safety.k, "window": safety.window,
                      "sensing": list(safety.sensing)}
            if ablated:
                params["ablation"] = {"sensing": ablation_sensing, "budget": safety.false_activation_budget,
                                      "rules": [rule for rule in safety.ablation if rule == "uncertainty-only"],
                                      "tradeoff_budgets": extra_budgets, "tradeoff_repeats": safety.tradeoff_repeats,
                                      "unperturbed": perturbation == first}
            evaluations.append(Unit(f"safety/{estimator}/{perturbation}", "safety_eval", params,
                                    deps=deps + calibrations))
    if proximity_calibration is not None:
        for perturbation, strengths in safety.perturbations.items():
            evaluations.append(Unit(f"safety/{NO_ESTIMATOR}/{perturbation}", "safety_eval_proximity", {
                **common, "perturbation": perturbation, "strengths": strengths, "repeats": safety.repeats,
                "window": safety.window, "sensing": ablation_sensing,
                "budgets": [safety.false_activation_budget, *extra_budgets], "unperturbed": perturbation == first,
                "tradeoff_repeats": safety.tradeoff_repeats,
            }, deps=(*acting, proximity_calibration.id)))
    if not ablated:
        return units + evaluations  # the configured order
    return sorted(units, key=_relative_cost, reverse=True) + sorted(evaluations, key=_relative_cost, reverse=True)


def _relative_cost(unit: Unit) -> float:
    """A unit's rough cost relative to a one-budget MC-dropout calibration, for the plan order: the runner starts
    ready units in plan order, so the longest first keep both workers busy to the end. Measured on the 2-core
    machine (Table 3 quick): an ensemble replay costs ~1.2 MC-dropout ones, a replay without estimate ~0.2; each
    further trade-off budget adds ~35 % replays (~5 % with the light search), the uncertainty-only search has ~15 %
    fewer candidates."""
    p = unit.params
    per_replay = {"ensemble": 1.2, "mc": 1.0}.get(p.get("estimator") or NO_ESTIMATOR, 0.2)
    per_budget = 0.05 if p.get("tradeoff_search") == "light" else 0.35
    replays = ((1.0 + per_budget * len(p.get("tradeoff_budgets", [])))
               * (0.85 if p.get("conditions") == "uncertainty-only" else 1.0))
    return per_replay * replays
