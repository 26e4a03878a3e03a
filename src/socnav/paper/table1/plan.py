"""The planner of Table 1's experiments (kind ``table1``): every algorithm trained on every training scenario with
every seed, each trained policy evaluated in every evaluation scenario.
"""

from __future__ import annotations

from socnav.experiments.registry import register_planner
from socnav.experiments.spec import Experiment
from socnav.experiments.units import Unit
from socnav.paper.train_eval import eval_unit_id, train_unit

__all__ = ["plan_train_eval"]


def count_train_eval(experiment: Experiment) -> int:
    """The units `plan_train_eval` builds, from the grid's sizes alone."""
    grid = experiment.grid
    trainings = len(grid.train_scenarios) * len(grid.algorithms) * len(grid.seeds)  # type: ignore[arg-type]
    return trainings * (1 + len(experiment.evaluation.scenarios))


@register_planner("table1", count=count_train_eval)
def plan_train_eval(experiment: Experiment) -> list[Unit]:
    """One training unit per (training scenario, algorithm, seed); one evaluation unit per trained policy and
    evaluation scenario, depending on its training unit."""
    grid, evaluation = experiment.grid, experiment.evaluation
    trains: list[Unit] = []
    evals: list[Unit] = []
    for scenario in grid.train_scenarios:
        for algo in grid.algorithms:
            for seed in grid.seeds:  # type: ignore[union-attr]
                train = train_unit(experiment, scenario, algo, seed)
                trains.append(train)
                for eval_scenario in evaluation.scenarios:
                    evals.append(Unit(eval_unit_id(scenario, algo, seed, eval_scenario), "eval", {
                        "train_scenario": scenario, "algo": algo, "train_seed": seed,
                        "eval_scenario": eval_scenario, "env": experiment.env_config(eval_scenario),
                        "episodes": evaluation.episodes, "seed": evaluation.seed, "n_envs": evaluation.n_envs,
                        "deterministic": evaluation.deterministic,
                    }, deps=(train.id,)))
    return trains + evals
