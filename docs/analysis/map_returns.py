"""What the reward pays for each way an episode ends (docs/maps.md, "Learning among walls"): the mean return per
outcome of the ORCA robot (with the planner), a robot that never moves and, optionally, learned policies, in one
world, on the same episodes. A policy maximises the return: if ending at a wall returns more than getting through,
that is what it learns.

    python docs/analysis/map_returns.py --config configs/env/doorway_route.yaml --episodes 200 --seed 100000 \
        --model runs/doorway_1m.zip
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

import socnav
from socnav.controllers import make_controller
from socnav.envs.rollout import rollout_episodes


class StandStill:
    """A robot that never moves: speed action -1, no turn."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        actions = np.zeros((len(observation["robot"]), 2), dtype=np.float32)
        actions[:, 0] = -1.0
        return actions, None


def returns_table(records: dict[str, pd.DataFrame]) -> str:
    """One Markdown row per controller: the mean return over all episodes, then per outcome `count (mean return)`."""
    outcomes = ["goal", "collision", "collision_wall", "timeout"]
    header = " | ".join(f"{name}: episodes (mean return)" for name in outcomes)
    lines = [f"| controller | mean return | {header} |", "|:--|--:|" + "--:|" * len(outcomes)]
    for name, frame in records.items():
        cells = []
        for outcome in outcomes:
            chosen = frame.loc[frame["outcome"] == outcome, "return"]
            cells.append(f"{len(chosen)} ({chosen.mean():.1f})" if len(chosen) else "0")
        lines.append(f"| {name} | {frame['return'].mean():.1f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=100_000)
    parser.add_argument("--model", nargs="*", default=[], help="learned policies (files) to include")
    args = parser.parse_args()
    config = socnav.load_config(args.config)
    controllers = {"ORCA robot": make_controller("orca", config), "never moves": StandStill()}
    controllers.update({path: socnav.load_policy(path) for path in args.model})
    records = {name: rollout_episodes(controller, config, args.episodes, seed=args.seed, n_envs=50, progress=False)
               for name, controller in controllers.items()}
    print(returns_table(records))


if __name__ == "__main__":
    main()
