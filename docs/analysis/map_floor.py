"""The floor of each map scenario (docs/maps.md, "Global planner"): how often people walk into a robot that never
moves, beside the ORCA robot with and without the global planner on the same episodes, in the default world.

    python docs/analysis/map_floor.py --episodes 200 --seed 0

A collision of the robot that stands still is one no robot avoids by stopping: the benchmark's floor.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.stats import binomtest

from socnav.config import load_config
from socnav.controllers import make_controller
from socnav.envs.rollout import rollout_episodes
from socnav.sim.scenarios import get_scenario, scenario_names


class StandStill:
    """A robot that never moves (speed action -1, no turn)."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        return np.tile(np.array([[-1.0, 0.0]], dtype=np.float32), (len(observation["robot"]), 1)), None


def _rate(hits: int, n: int) -> str:
    interval = binomtest(hits, n).proportion_ci(0.95, method="exact")
    return f"{100 * hits / n:.1f} [{100 * interval.low:.1f}, {100 * interval.high:.1f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print("| scenario | robot | Goal % [95 % CI] | Collision with people % [95 % CI] | Wall % | Time-out % |")
    print("|:--|:--|--:|--:|--:|--:|")
    for scenario in [name for name in scenario_names(self_contained=True)
                     if getattr(get_scenario(name), "has_map", False)]:
        config = load_config({"scenario": scenario})
        straight = load_config({"scenario": scenario, "planner": {"enabled": False}})  # humans too: no planner
        for label, robot, world in [("stands still", StandStill(), config),
                                    ("ORCA, planner off", make_controller("orca", straight), straight),
                                    ("ORCA, planner on", make_controller("orca", config), config)]:
            records = rollout_episodes(robot, world, args.episodes, seed=args.seed, n_envs=50)
            n, outcome = len(records), records["outcome"]
            print(f"| {scenario} | {label} | {_rate(int((outcome == 'goal').sum()), n)} | "
                  f"{_rate(int((outcome == 'collision').sum()), n)} | "
                  f"{100 * (outcome == 'collision_wall').mean():.1f} | {100 * (outcome == 'timeout').mean():.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()
