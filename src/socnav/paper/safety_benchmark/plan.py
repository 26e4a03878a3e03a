"""The planner of the safety-layer benchmark (kind ``safety_benchmark``): the policies of the grid, then one benchmark
unit per training seed.
"""

from __future__ import annotations

from socnav.config import ConfigError, load_config
from socnav.experiments.registry import register_planner
from socnav.experiments.spec import Experiment, ExperimentError
from socnav.experiments.units import Unit
from socnav.paper.safety_benchmark.benchmark import replay_shift
from socnav.paper.train_eval import train_unit

__all__ = ["plan_safety_benchmark"]


def count_safety_benchmark(experiment: Experiment) -> int:
    """The units `plan_safety_benchmark` builds: a training and a benchmark unit per training seed."""
    grid = experiment.grid
    return 2 * len(grid.train_scenarios) * len(grid.algorithms) * len(grid.seeds)  # type: ignore[arg-type]


@register_planner("safety_benchmark", count=count_safety_benchmark)
def plan_safety_benchmark(experiment: Experiment) -> list[Unit]:
    """The safety-layer benchmark (`socnav.paper.safety_benchmark.benchmark`): train the policies of `grid` (one
    scenario, one algorithm), then one benchmark unit per training seed, in which that seed's policy acts and its
    MC dropout estimates the uncertainty: every trigger of `safety.triggers` calibrated at every budget of
    `safety.tradeoff_budgets` (or `safety.false_activation_budget`) on the calibration episodes, then played on the
    held-out worlds (`safety.perturbations` and the benchmark's shifts)."""
    grid, evaluation, safety = experiment.grid, experiment.evaluation, experiment.safety
    if safety is None or len(grid.train_scenarios) != 1 or len(grid.algorithms) != 1:
        raise ExperimentError(f"experiment {experiment.name!r}: kind safety_benchmark needs a `safety` block and "
                              "trains one algorithm on one scenario")
    scenario, algo = grid.train_scenarios[0], grid.algorithms[0]
    trains = [train_unit(experiment, scenario, algo, seed) for seed in grid.seeds]  # type: ignore[union-attr]
    budgets = list(safety.tradeoff_budgets) or [safety.false_activation_budget]
    benchmarks = [Unit(f"benchmark/seed{train.params['seed']}", "safety_benchmark", {
        "env": experiment.env_config(scenario), "train_seed": train.params["seed"], "budgets": budgets,
        "calibration_episodes": safety.calibration_episodes, "episodes": evaluation.episodes,
        "seed": evaluation.seed, "n_envs": evaluation.n_envs, "perturbations": safety.perturbations,
        "sensing": safety.sensing[0], "k": safety.k, "window": safety.window, "triggers": list(safety.triggers),
        **_replay_files(experiment, scenario),
    }, deps=(train.id,)) for train in trains]
    return [*trains, *benchmarks]


def _replay_files(experiment: Experiment, scenario: str) -> dict[str, list[str]]:
    """``{"replay_files": [absolute paths]}`` of the benchmark's replay shift, each file checked as the world
    reading it checks it; ``{}`` without files (the units' parameters as before the shift existed)."""
    files = experiment.safety.replay_files if experiment.safety is not None else []
    if not files:
        return {}
    world = {**experiment.env_config(scenario), **replay_shift(files)["replay"]}
    try:
        checked = load_config(world).humans.replay.files
    except ConfigError as error:
        raise ExperimentError(f"experiment {experiment.name!r}: safety.replay_files: {error}") from None
    return {"replay_files": [str(path) for path in checked]}
